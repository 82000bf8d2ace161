"""The live service (``canrls run``): frames in from the bus, estimates out on the bus.

::

    bus --Notifier--> _RxListener (queue) --> estimator thread:
        FrameProcessor (decoder + pairer + Pipeline: the same as ``canrls fit``,
            float and fixed RLS); commands (RlsCommand -> RlsCommandAck);
        publications (RlsEstimate/Sigma/Reference, RlsStatus/Health every
            publish_interval; RlsParamInfo/RlsCounters every info_interval);
        checkpoints (every checkpoint_interval, and at stop)
    supervisor thread: reopens a vanished bus with backoff, pings the systemd watchdog

Threads: python-can's :class:`~can.Notifier` reads the bus and hands every frame to
a listener that only queues it; the estimator thread takes whatever has arrived (at
most every ``block_interval``, by default the publish interval, and right before each
publication; at once when a command frame waits) and processes it as one block through
:class:`~canrls.processor.FrameProcessor`, so a log of the frames the daemon saw,
replayed offline, gives the same parameters bit for bit. Command frames are applied
in stream order between the frames around them. Nothing the estimator does waits
for the bus: frames are sent with ``timeout=send_timeout`` (0: non-blocking) and a
frame the interface cannot take is dropped and counted (``TxDropped``).

Bus faults: an error frame (SocketCAN delivers them, bus-off included) sets the
``BusFault`` flag and pauses transmission for ``fault_hold_s`` after the last one
(a ``CAN_ERR_RESTARTED`` frame ends a bus-off pause at once). An exception from the
bus's ``recv`` (interface gone: unplugged adapter, ``ip link set can0 down``) makes
the supervisor stop the notifier, shut the bus down and reopen it with exponential
backoff from ``reopen_min_s`` to ``reopen_max_s``; the estimator keeps its state.

The bus is opened with ``can.Bus(..., ignore_config=True)`` from the ``[can]`` table
and the command line only: python-can's own configuration sources (``can.rc``,
``$CAN_INTERFACE``/``$CAN_CHANNEL``/``$CAN_BITRATE``/``$CAN_CONFIG``, ``/etc/can.conf``,
``~/.can``, ``~/.canrc``) are never read, so a stray file cannot redirect the service.

See ``docs/daemon.md`` for the ``[daemon]`` keys, commands, checkpoints and systemd.
"""

from __future__ import annotations

import collections
import dataclasses
import gc
import json
import logging
import math
import signal
import sys
import threading
import time
import weakref
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np

from canrls.can.frameblock import FrameBlock
from canrls.can.frames import (
    Command,
    CommandCode,
    CommandFrameError,
    CommandResult,
    EffectId,
    EquationId,
    ParameterReport,
    StatusReport,
    decode_command,
    encode_ack,
    encode_param_info,
    encode_parameters,
    encode_status,
    frame_ids,
)
from canrls.can.protocol import FeedbackEncoder, Protocol
from canrls.config import AppConfig
from canrls.errors import BusError, CheckpointError, ConfigError
from canrls.estimation.model import Model
from canrls.estimation.pipeline import (
    Estimates,
    EstimatorSettings,
    Pipeline,
    PipelineBlock,
    divergence,
)
from canrls.estimation.rls import RLSFlag
from canrls.live.checkpoint import Checkpoint, load_checkpoint, save_checkpoint, set_aside
from canrls.live.sdnotify import SystemdNotifier
from canrls.processor import FrameProcessor

__all__ = [
    "DaemonSettings",
    "DaemonStats",
    "Daemon",
    "bus_config",
    "open_bus",
    "messages_to_block",
    "command_effect_name",
    "fingerprint",
    "COMMAND_ID",
]

log = logging.getLogger(__name__)

#: Arbitration ID of ``RlsCommand`` in the default DBC.
COMMAND_ID = frame_ids().command
_COUNTERS_ID = frame_ids().counters
_WINDUP = int(RLSFlag.WINDUP)
# SocketCAN error classes (linux/can/error.h) in an error frame's arbitration ID
_CAN_ERR_BUSOFF = 0x40
_CAN_ERR_RESTARTED = 0x100

_DAEMON_KEYS: dict[str, str] = {
    "publish_interval": "seconds between parameter/status publications (0: after every block)",
    "info_interval": "seconds between RlsParamInfo and RlsCounters",
    "block_interval": "seconds the estimator lets frames gather before processing them "
                      "(default: publish_interval)",
    "commands": "accept RlsCommand frames (false: every command is answered 'disabled')",
    "checkpoint": "checkpoint file ('' or absent: none)",
    "checkpoint_interval": "seconds between checkpoints",
    "queue_size": "frames held between the bus and the estimator; beyond, dropped and counted",
    "max_block": "most frames processed in one block",
    "send_timeout": "seconds a transmission may wait (0: never block)",
    "fault_hold_s": "seconds transmission stays paused after the last error frame",
    "reopen_min_s": "first delay before reopening a vanished bus",
    "reopen_max_s": "longest delay between reopening attempts",
    "divergence_limit": "float-vs-fixed divergence above which the Diverged flag is set",
    "record": "log file of every frame received (python-can writer by suffix: .log, .asc, .blf)",
    "model_file": "TOML file whose [model] replaces the configuration's (re-read on SIGHUP)",
    "switch_interval": "Python's thread switch interval while running, seconds (0: leave it)",
}


# ----------------------------------------------------------------------- settings
@dataclass(frozen=True)
class DaemonSettings:
    """The ``[daemon]`` table (see :data:`_DAEMON_KEYS` and ``docs/daemon.md``)."""

    publish_interval: float = 0.1
    info_interval: float = 1.0
    #: ``None``: the publish interval (see :attr:`block_s`)
    block_interval: float | None = None
    commands: bool = True
    checkpoint: Path | None = None
    checkpoint_interval: float = 60.0
    queue_size: int = 1_000_000
    max_block: int = 65536
    send_timeout: float = 0.0
    fault_hold_s: float = 1.0
    reopen_min_s: float = 0.5
    reopen_max_s: float = 30.0
    divergence_limit: float = 0.1
    record: Path | None = None
    model_file: Path | None = None
    switch_interval: float = 0.001

    def __post_init__(self) -> None:
        src = "daemon"
        for k in ("publish_interval", "block_interval", "send_timeout", "switch_interval"):
            v = getattr(self, k)
            if k == "block_interval" and v is None:
                continue
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"{src}.{k} = {v!r}: must be >= 0 seconds")
        for k in ("info_interval", "checkpoint_interval", "fault_hold_s", "reopen_min_s",
                  "reopen_max_s", "divergence_limit"):
            v = getattr(self, k)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"{src}.{k} = {v!r}: must be > 0")
        if self.reopen_max_s < self.reopen_min_s:
            raise ConfigError(f"{src}.reopen_max_s = {self.reopen_max_s!r}: must be >= "
                              f"reopen_min_s ({self.reopen_min_s!r})")
        for k in ("queue_size", "max_block"):
            if getattr(self, k) < 1:
                raise ConfigError(f"{src}.{k} = {getattr(self, k)!r}: must be >= 1")

    @property
    def block_s(self) -> float:
        """Seconds the estimator lets frames gather: ``block_interval``, by default the
        publish interval. Each block has a fixed cost of its own (some 1 ms of CPU on
        the development machine, the caches being cold after the wait), so blocks more
        frequent than publications cost CPU without fresher parameter frames."""
        return self.publish_interval if self.block_interval is None else self.block_interval

    @classmethod
    def from_table(cls, table: Mapping[str, Any], source: str = "<config>",
                   base_dir: Path | None = None) -> DaemonSettings:
        """Validate a ``[daemon]`` table; errors name the file, the key and the value."""
        kw: dict[str, Any] = {}
        for k, v in table.items():
            key = f"{source}: daemon.{k}"
            if k not in _DAEMON_KEYS:
                raise ConfigError(f"{key} = {v!r}: unknown key (valid: "
                                  f"{', '.join(_DAEMON_KEYS)})")
            if k == "commands":
                if not isinstance(v, bool):
                    raise ConfigError(f"{key} = {v!r}: must be true or false")
                kw[k] = v
            elif k in ("queue_size", "max_block"):
                if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                    raise ConfigError(f"{key} = {v!r}: must be an integer >= 1")
                kw[k] = v
            elif k in ("checkpoint", "record", "model_file"):
                if not isinstance(v, str):
                    raise ConfigError(f"{key} = {v!r}: must be a file path")
                if v:
                    p = Path(v).expanduser()
                    kw[k] = p if p.is_absolute() or base_dir is None else base_dir / p
            else:
                if isinstance(v, bool) or not isinstance(v, int | float):
                    raise ConfigError(f"{key} = {v!r}: must be a number of seconds")
                kw[k] = float(v)
        try:
            return cls(**kw)
        except ConfigError as e:
            raise ConfigError(f"{source}: {e}") from e

    @classmethod
    def from_config(cls, cfg: AppConfig) -> DaemonSettings:
        return cls.from_table(cfg.daemon, cfg.source, cfg.base_dir)


# ----------------------------------------------------------------------- the bus
_BUS_KEYS = ("interface", "channel", "bitrate", "fd", "data_bitrate")


def bus_config(cfg: AppConfig | None = None, args: Any = None) -> dict[str, Any]:
    """Every argument of the bus, explicitly: ``[can]`` overridden by the command line.

    ``args`` is a namespace from :func:`canrls.cli._common.add_bus_options`
    (``-i -c -b --fd --data-bitrate --timing --bus-kwargs``).

    :raises ConfigError: no interface, or a value of the wrong type.
    """
    conf: dict[str, Any] = {}
    src = cfg.source if cfg is not None else "<command line>"
    if cfg is not None:
        for k in _BUS_KEYS:
            if k in cfg.can:
                conf[k] = cfg.can[k]
    if args is not None:
        for k in (*_BUS_KEYS, "timing"):
            if getattr(args, k, None) is not None:
                conf[k] = getattr(args, k)
        conf.update(getattr(args, "bus_kwargs", None) or {})
    if not conf.get("interface"):
        raise ConfigError(f"{src}: no CAN interface: set can.interface in the configuration or "
                          f"-i/--interface (socketcan, virtual, canrls-sim, remote, ...)")
    if not isinstance(conf["interface"], str):
        raise ConfigError(f"{src}: can.interface = {conf['interface']!r}: must be a string")
    for k in ("bitrate", "data_bitrate"):
        v = conf.get(k)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v <= 0):
            raise ConfigError(f"{src}: can.{k} = {v!r}: must be a positive integer (bit/s)")
    if "fd" in conf and not isinstance(conf["fd"], bool):
        raise ConfigError(f"{src}: can.fd = {conf['fd']!r}: must be true or false")
    return conf


def open_bus(config: Mapping[str, Any]) -> can.BusABC:
    """``can.Bus(**config, ignore_config=True)``: python-can's config files and
    environment variables are not consulted.

    :raises BusError: the interface cannot be opened (names interface and channel).
    """
    conf = dict(config)
    try:
        return can.Bus(ignore_config=True, **conf)
    except (can.CanError, OSError, ValueError, ImportError, TypeError, NotImplementedError) as e:
        raise BusError(f"cannot open CAN interface {conf.get('interface')!r} channel "
                       f"{conf.get('channel')!r}: {e}") from e


def messages_to_block(msgs: Sequence[can.Message]) -> FrameBlock:
    """:meth:`FrameBlock.from_messages`, vectorised (the same block, field for field)."""
    n = len(msgs)
    if n == 0:
        return FrameBlock.empty()
    datas = [m.data for m in msgs]
    lens = [len(d) for d in datas]
    width = max(8, max(lens))
    if min(lens) == width:
        data = np.frombuffer(b"".join(datas), np.uint8).reshape(n, width).copy()
    else:
        data = np.frombuffer(b"".join(bytes(d).ljust(width, b"\0") for d in datas),
                             np.uint8).reshape(n, width).copy()
    return FrameBlock(
        t=np.array([m.timestamp for m in msgs], np.float64),
        arbitration_id=np.array([m.arbitration_id for m in msgs], np.uint32),
        is_extended=np.array([m.is_extended_id for m in msgs], np.bool_),
        is_remote=np.array([m.is_remote_frame for m in msgs], np.bool_),
        is_error=np.array([m.is_error_frame for m in msgs], np.bool_),
        dlc=np.array(lens, np.uint8),
        data=data,
    )


def command_effect_name(effect: EffectId, order: int, model: Model) -> str:
    """The model's name of the effect a command means: ``cogging:K``, ``user:NAME``...

    :raises CommandFrameError: a user term index the configuration does not have.
    """
    if effect is EffectId.COGGING:
        return f"cogging:{order}"
    if effect is EffectId.USER:
        names = list(model.terms)
        if not 0 < order <= len(names):
            raise CommandFrameError(f"no user term {order} in the configuration "
                                    f"({len(names)} defined)", CommandResult.UNKNOWN_EFFECT)
        return f"user:{names[order - 1]}"
    return effect.effect_name


def _plain(d: Any) -> Any:
    """A JSON round trip: tuples become lists, as a checkpoint stores them."""
    return json.loads(json.dumps(d, allow_nan=True))


def fingerprint(settings: EstimatorSettings, dt: float) -> dict[str, Any]:
    """What besides the model must match for a checkpoint to resume: ``dt`` and every
    estimator setting (the forgetting factor too: ``set_lambda`` lives in the state)."""
    d: dict[str, Any] = {"dt": dt}
    for f in dataclasses.fields(settings):
        v = getattr(settings, f.name)
        if isinstance(v, Mapping):
            v = {str(k): repr(x) for k, x in sorted(v.items())}
        elif not (v is None or isinstance(v, bool | int | float | str)):
            v = repr(v)
        d[f.name] = v
    return _plain(d)


# ----------------------------------------------------------------------- interpreter
class _InterpreterTuning:
    """Process-wide settings for latency while at least one daemon runs.

    * The bus reader (python-can's notifier thread) and the estimator share the GIL.
      With CPython's default switch interval (5 ms) a thread that is ready waits up
      to 5 ms while another runs Python code without blocking, e.g. the notifier
      taking frames already queued by python-can's virtual bus. ``switch_interval``
      (``sys.setswitchinterval``) shortens that wait.
    * ``gc.freeze()`` moves every object alive at start (imported modules, numba's
      registries: some 65 000 objects) out of the cyclic collector's reach, so an
      occasional full collection no longer costs tens of milliseconds.

    The first daemon to start applies them, the last to stop restores the
    interpreter's settings (``gc.unfreeze()``).
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._users = 0
        self._saved = 0.0

    def tune(self, switch_interval: float) -> None:
        with self._lock:
            self._users += 1
            if self._users == 1:
                self._saved = sys.getswitchinterval()
                if switch_interval > 0:
                    sys.setswitchinterval(switch_interval)
                gc.freeze()

    def restore(self) -> None:
        with self._lock:
            self._users -= 1
            if self._users == 0:
                sys.setswitchinterval(self._saved)
                gc.unfreeze()


_interpreter = _InterpreterTuning()


# ----------------------------------------------------------------------- listener
class _RxListener(can.Listener):
    """Runs in the notifier's thread: queues each frame, nothing more."""

    def __init__(self, daemon: Daemon, limit: int, block: bool) -> None:
        self.daemon = daemon
        self.queue: collections.deque[can.Message] = collections.deque()
        self.wake = threading.Event()
        #: set when a command frame is queued (or the input closes): the estimator
        #: stops letting frames gather and takes them at once
        self.hurry = threading.Event()
        self.space = threading.Event()
        self.limit = limit
        self.block = block
        self.received = 0
        self.overflow = 0
        self.recorder: can.Listener | None = None
        self._cpu0: float | None = None
        self.cpu = 0.0
        #: open while set; :meth:`Daemon.hold_input` closes it
        self.gate = threading.Event()
        self.gate.set()

    def on_message_received(self, msg: can.Message) -> None:
        while not self.gate.is_set() and not self.daemon._stopping.is_set():
            self.gate.wait(0.05)
        q = self.queue
        if len(q) >= self.limit:
            if not self.block:
                self.overflow += 1
                return
            while len(q) >= self.limit and not self.daemon._stopping.is_set():
                self.space.clear()
                self.space.wait(0.05)
        q.append(msg)
        if msg.arbitration_id == COMMAND_ID and not msg.is_extended_id:
            self.hurry.set()
        if self.recorder is not None:
            self.recorder.on_message_received(msg)
        self.received += 1
        if self.received & 255 == 1:
            now = time.thread_time()
            if self._cpu0 is None:
                self._cpu0 = now
            self.cpu = now - self._cpu0
        if not self.wake.is_set():
            self.wake.set()

    def on_error(self, exc: Exception) -> None:
        self.daemon._bus_failed(exc)
        time.sleep(0.05)  # the notifier retries recv at once: do not spin

    def stop(self) -> None:
        """The notifier stops (bus reopened or daemon stopping): the queue stays."""


# ----------------------------------------------------------------------- stats
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
    reloads: int = 0
    checkpoints: int = 0
    backlog: int = 0
    estimator_cpu_s: float = 0.0
    listener_cpu_s: float = 0.0
    resumed_from: str | None = None
    counters: dict[str, int] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


# ----------------------------------------------------------------------- the daemon
class Daemon:
    """The live estimator on a CAN bus.

    :param protocol: DBC and signal mapping of the drive's feedback.
    :param model: the configured model (a checkpoint may resume with effects added to it).
    :param settings: estimator settings (as ``canrls fit``).
    :param daemon: the ``[daemon]`` settings.
    :param bus: bus arguments for :func:`open_bus` (from :func:`bus_config`).
    :param bus_factory: opens the bus instead (tests: a faulty bus); called again to reopen.
    :param reload: returns the configured model again (SIGHUP); None: reload does nothing.
    :param notifier: systemd notifications (default: from ``$NOTIFY_SOCKET``).
    :param backpressure: when the queue is full, make the bus reader wait instead of
        dropping frames (only for simulated buses, whose drive then waits too).
    :param on_publish: called in the estimator thread after each publication with
        ``(frames processed so far, time.monotonic() when its parameter frames had
        been sent)`` (benchmarks).
    """

    def __init__(self, protocol: Protocol, model: Model,
                 settings: EstimatorSettings | None = None,
                 daemon: DaemonSettings | None = None, *,
                 bus: Mapping[str, Any] | None = None,
                 bus_factory: Callable[[], can.BusABC] | None = None,
                 reload: Callable[[], Model] | None = None,
                 notifier: SystemdNotifier | None = None,
                 backpressure: bool = False,
                 on_publish: Callable[[int, float], None] | None = None) -> None:
        if bus is None and bus_factory is None:
            raise ConfigError("Daemon: give the bus arguments (bus=...) or a bus_factory")
        self.protocol = protocol
        self.settings = settings or EstimatorSettings()
        self.config = daemon or DaemonSettings()
        self._bus_args = dict(bus or {})
        self._bus_factory = bus_factory or (lambda: open_bus(self._bus_args))
        self._reload_fn = reload
        self.sd = notifier if notifier is not None else SystemdNotifier()
        self._on_publish = on_publish
        self.config_model = model
        self._proc = FrameProcessor(protocol, model, self.settings)
        self.dt = self._proc.pipeline.dt
        self._fingerprint = fingerprint(self.settings, self.dt)
        self._lock = threading.RLock()
        self._stopping = threading.Event()
        self._stopped = threading.Event()
        self._rx_closed = threading.Event()
        self._reload_requested = threading.Event()
        self._failed = threading.Event()
        self._fail_exc: BaseException | None = None
        self._rx = _RxListener(self, self.config.queue_size, backpressure)
        self._bus: can.BusABC | None = None
        self._notifier: can.Notifier | None = None
        self._threads: list[threading.Thread] = []
        self._recorder: can.Listener | None = None
        self._started = False
        self._tuned = False
        self._heartbeat = time.monotonic()
        # counters
        self._c: dict[str, int] = collections.Counter()
        self._base: dict[str, int] = {}
        self._est_cpu = 0.0
        self._pub_counter = 0
        self._ack_counter = 0
        self._fault_until = 0.0
        self._bus_off = False
        self._fault_active = False
        self._window_windup = False
        #: estimators whose non-finite samples were logged (once each)
        self._warned_nonfinite: weakref.WeakSet[Any] = weakref.WeakSet()
        self._last_lost = 0
        self._last_sat = 0
        self._low_excitation = False
        self._online_rms = [math.nan] * len(self._proc.pipeline.estimators)
        self._info_due = 0.0
        self._publish_now = False
        self.resumed_from: str | None = None
        self.last_status: StatusReport | None = None
        if self.config.checkpoint is not None:
            self._resume(self.config.checkpoint)

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
        return self._bus

    def estimates(self) -> Estimates:
        """The current estimates (taken under the estimator's lock)."""
        with self._lock:
            return self._proc.pipeline.estimates()

    def stats(self) -> DaemonStats:
        c = self._c
        with self._lock:
            counters = self._wire_counters()
        return DaemonStats(
            frames=self._proc.frames + self._base.get("frames", 0),
            samples=self._proc.pipeline.samples, blocks=c["blocks"],
            publications=c["publications"], frames_sent=c["frames_sent"],
            tx_dropped=c["tx_dropped"] + self._base.get("tx_dropped", 0),
            tx_paused=c["tx_paused"],
            rx_overflow=self._rx.overflow, error_frames=c["error_frames"],
            bus_reopens=c["bus_reopens"], commands=c["commands"],
            commands_rejected=c["commands_rejected"], reloads=c["reloads"],
            checkpoints=c["checkpoints"], backlog=len(self._rx.queue),
            estimator_cpu_s=self._est_cpu, listener_cpu_s=self._rx.cpu,
            resumed_from=self.resumed_from, counters=counters)

    def status(self) -> StatusReport:
        """The status as the next RlsStatus/RlsHealth/RlsCounters would carry it."""
        with self._lock:
            return self._status(time.monotonic())

    def parameter_reports(self) -> list[ParameterReport]:
        with self._lock:
            return self._reports()[0]

    # ------------------------------------------------------------------ checkpoint
    def _resume(self, path: Path) -> None:
        if not path.exists():
            log.info("no checkpoint at %s: starting from the prior", path)
            return
        try:
            cp = load_checkpoint(path)
            if cp.config_model != _plain(self.config_model.to_dict()):
                raise CheckpointError(f"{path}: checkpoint was taken with another configured "
                                      f"model ({cp.config_model.get('effects')})")
            if cp.fingerprint != self._fingerprint:
                diff = sorted(k for k in set(cp.fingerprint) | set(self._fingerprint)
                              if cp.fingerprint.get(k) != self._fingerprint.get(k))
                raise CheckpointError(f"{path}: checkpoint was taken with other estimator "
                                      f"settings ({', '.join(diff)})")
            model = Model.from_dict(cp.model, source=f"{path} (checkpoint)",
                                    available_signals=self.config_model.available_signals)
            pipeline = Pipeline(model, self.dt, self.settings)
            pipeline.restore(cp.state)
        except (CheckpointError, ConfigError, KeyError, ValueError, TypeError, IndexError) as e:
            where = set_aside(path)
            log.error("checkpoint %s not loaded (%s); set aside as %s", path, e, where)
            return
        self._proc.pipeline = pipeline
        self._online_rms = [math.nan] * len(pipeline.estimators)
        self._base = dict(cp.counters)
        self.resumed_from = str(path)
        log.info("resumed from checkpoint %s (%d samples, effects %s, saved %s)", path,
                 pipeline.samples, ",".join(model.effect_names),
                 time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(cp.saved_at)))

    def checkpoint(self) -> Path | None:
        """Save a checkpoint now (no-op without ``[daemon] checkpoint``)."""
        path = self.config.checkpoint
        if path is None:
            return None
        with self._lock:
            counters = self._wire_counters()
            counters["frames"] = self._proc.frames + self._base.get("frames", 0)
            cp = Checkpoint(model=_plain(self.model.to_dict()),
                            config_model=_plain(self.config_model.to_dict()),
                            fingerprint=self._fingerprint, state=self._proc.pipeline.state(),
                            counters=counters, saved_at=time.time())
        try:
            save_checkpoint(path, cp)
        except OSError as e:
            log.error("checkpoint %s: cannot write: %s", path, e)
            return None
        self._c["checkpoints"] += 1
        log.debug("checkpoint written to %s", path)
        return path

    # ------------------------------------------------------------------ life cycle
    def start(self) -> None:
        """Open the bus and start the threads (``BusError`` if the bus cannot be opened)."""
        if self._started:
            raise RuntimeError("daemon already started")
        self._started = True
        try:
            self._warm_up()
        except Exception as e:  # only a speed-up: never a reason not to start
            log.warning("warm-up skipped (the first frames will be slower): %s", e)
        if self.config.record is not None:
            self._recorder = can.Logger(str(self.config.record))
            self._rx.recorder = self._recorder
        try:
            self._open()
        except BaseException:
            self._close_recorder()
            raise
        self._heartbeat = time.monotonic()
        _interpreter.tune(self.config.switch_interval)
        self._tuned = True
        for target, name in ((self._estimator_loop, "canrls estimator"),
                             (self._supervisor_loop, "canrls supervisor")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        log.info("canrls daemon running on %s: effects %s, %d parameters", self._bus_info(),
                 ",".join(self.model.effect_names), len(self.model.parameters))

    def _warm_up(self) -> FrameProcessor:
        """Run the hot path once on made-up frames, before the bus opens; returns the
        throwaway processor.

        numba loads each compiled kernel from its cache at its first call (some
        100 ms in all), and the frame codecs are built at their first use: without
        this, the first frames after start would wait that long for their parameter
        frames. A throwaway processor takes the frames and nothing is sent: the
        daemon's own state does not change.
        """
        proc = FrameProcessor(self.protocol, self.model, self._proc.pipeline.settings,
                              period=self._proc.pairer.period)
        pipe = proc.pipeline
        n = max(e.warmup for e in pipe.estimators) + 64  # past the filter's warm-up
        t = np.arange(n) * pipe.dt
        hi = abs(self.model.ranges.get("speed", (0.0, 1.0))[1])
        # moving both ways at half the speed range, so every estimator updates
        omega = 0.5 * hi * np.sin(2 * math.pi * t / (t[-1] + pipe.dt))
        signals = {"current": 0.1 * np.cos(t), "speed": omega,
                   "position": np.cumsum(omega) * pipe.dt, "voltage": 0.1 * omega}
        proc.process(FeedbackEncoder(self.protocol, clip=True).encode(t, **signals))
        proc.flush()
        reports: list[ParameterReport] = []
        for e in pipe.estimators:
            e.rls.excitation()
        for b in self._layout_of(self._proc.pipeline)[1]:
            reports += [r.with_estimates(0.0, 0.0, 0.0, True) for r in b]
        encode_parameters(reports, 0)
        encode_status(StatusReport(), 0)
        encode_param_info(reports)
        encode_ack(0, CommandResult.OK, 0)
        return proc

    def stop(self) -> None:
        """Stop reading, process what was queued, checkpoint, close the bus. Idempotent."""
        if self._stopped.is_set() or not self._started:
            self._stopping.set()
            return
        self.sd.stopping()
        self._stopping.set()
        self._rx.space.set()
        for t in self._threads:  # the supervisor first: no reopening from now on
            if t.name == "canrls supervisor":
                t.join()
        self._close_notifier()
        self._rx_closed.set()  # the estimator drains the queue, then ends
        self._rx.hurry.set()
        self._rx.wake.set()
        for t in self._threads:
            t.join()
        self._threads.clear()
        self.checkpoint()
        self._close_bus()
        self._close_recorder()
        if self._tuned:
            self._tuned = False
            _interpreter.restore()
        self._stopped.set()
        log.info("canrls daemon stopped: %s", self.stats().to_dict())

    def __enter__(self) -> Daemon:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def request_stop(self) -> None:
        self._stopping.set()
        self._rx.wake.set()

    def request_reload(self) -> None:
        self._reload_requested.set()
        self._rx.wake.set()

    def run(self, duration: float | None = None) -> int:
        """Start, serve until SIGTERM/SIGINT (or ``duration`` s), stop; SIGHUP reloads.

        Signal handlers are installed only when called from the main thread.
        """
        handlers: dict[int, Any] = {}
        if threading.current_thread() is threading.main_thread():
            for sig, fn in ((signal.SIGTERM, lambda *_: self.request_stop()),
                            (signal.SIGINT, lambda *_: self.request_stop()),
                            (signal.SIGHUP, lambda *_: self.request_reload())):
                handlers[sig] = signal.signal(sig, fn)
        try:
            self.start()
            self.sd.ready(f"estimating {','.join(self.model.effect_names)} on "
                          f"{self._bus_info()}")
            end = None if duration is None else time.monotonic() + duration
            while not self._stopping.is_set():
                left = 0.2 if end is None else min(0.2, end - time.monotonic())
                if left <= 0:
                    break
                self._stopping.wait(left)
        finally:
            self.stop()
            for sig, old in handlers.items():
                signal.signal(sig, old)
        return 0

    def wait_for(self, predicate: Callable[[Daemon], bool], timeout: float) -> bool:
        """Poll ``predicate(self)`` until true or ``timeout`` seconds (tests, the demo)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if predicate(self):
                return True
            time.sleep(0.005)
        return predicate(self)

    # ------------------------------------------------------------------ bus handling
    def _bus_info(self) -> str:
        b = self._bus
        return str(getattr(b, "channel_info", None) or self._bus_args or "bus")

    def _open(self) -> None:
        bus = self._bus_factory()
        self._bus = bus
        self._failed.clear()
        self._notifier = can.Notifier(bus, [self._rx], timeout=0.1)

    def _close_notifier(self) -> None:
        n, self._notifier = self._notifier, None
        if n is not None:
            n.stop(timeout=5.0)

    def _close_bus(self) -> None:
        b, self._bus = self._bus, None
        if b is not None:
            try:
                b.shutdown()
            except (can.CanError, OSError) as e:
                log.debug("bus shutdown: %s", e)

    def _close_recorder(self) -> None:
        r, self._recorder = self._recorder, None
        self._rx.recorder = None
        if r is not None:
            r.stop()

    def _bus_failed(self, exc: BaseException) -> None:
        """Called in the notifier's thread when ``recv`` raises."""
        if not self._failed.is_set():
            self._fail_exc = exc
            self._failed.set()

    def _reopen(self) -> None:
        exc = self._fail_exc
        log.warning("CAN bus %s failed (%s): reopening", self._bus_info(), exc)
        self._close_notifier()
        self._close_bus()
        delay = self.config.reopen_min_s
        while not self._stopping.is_set():
            try:
                self._open()
            except BusError as e:
                log.warning("%s; next attempt in %.3g s", e, delay)
                if self._stopping.wait(delay):
                    return
                delay = min(delay * 2.0, self.config.reopen_max_s)
                continue
            self._c["bus_reopens"] += 1
            log.info("CAN bus reopened: %s", self._bus_info())
            return

    def _supervisor_loop(self) -> None:
        wd = self.sd.watchdog_interval
        next_ping = 0.0
        while not self._stopping.is_set():
            if self._failed.is_set():
                self._reopen()
                continue
            now = time.monotonic()
            if wd is not None and now >= next_ping:
                # alive = the estimator loop went round recently
                if now - self._heartbeat < wd / 2:
                    self.sd.watchdog()
                next_ping = now + wd / 4
            self._stopping.wait(0.05)

    def _send(self, msgs: Sequence[can.Message]) -> int:
        """Send without blocking the estimator; a refused frame is dropped and counted."""
        bus = self._bus
        now = time.monotonic()
        if bus is None or now < self._fault_until or self._failed.is_set():
            self._c["tx_paused"] += len(msgs)  # not attempted: the bus is faulty
            return 0
        sent = 0
        timeout = self.config.send_timeout
        for i, m in enumerate(msgs):
            try:
                bus.send(m, timeout=timeout)
                sent += 1
            except can.CanOperationError:
                self._c["tx_dropped"] += 1  # transmit queue full (ENOBUFS) or similar
            except (can.CanError, OSError) as e:
                # the interface refuses to send at all: pause like an error frame
                self._c["tx_dropped"] += len(msgs) - i
                self._fault(now, f"send failed: {e}")
                break
        self._c["frames_sent"] += sent
        return sent

    def _fault(self, now: float, why: str) -> None:
        if not self._fault_active:
            log.warning("CAN bus fault (%s): transmission paused", why)
        self._fault_active = True
        self._fault_until = now + self.config.fault_hold_s

    def _error_frame(self, msg: can.Message) -> None:
        self._c["error_frames"] += 1
        now = time.monotonic()
        cls = msg.arbitration_id
        if cls & _CAN_ERR_RESTARTED and not cls & _CAN_ERR_BUSOFF:
            if self._bus_off:
                log.info("CAN controller restarted after bus-off")
            self._bus_off = False
            self._fault_until = now  # resume at once
            return
        if cls & _CAN_ERR_BUSOFF:
            self._bus_off = True
        self._fault(now, f"error frame 0x{cls:X}{' (bus-off)' if self._bus_off else ''}")

    # ------------------------------------------------------------------ estimator thread
    def _estimator_loop(self) -> None:
        cfg = self.config
        now = time.monotonic()
        next_pub = now + cfg.publish_interval
        self._info_due = now
        next_ckpt = now + cfg.checkpoint_interval
        last_block = 0.0
        cpu0 = time.thread_time()
        rx = self._rx
        try:
            while True:
                closed = self._rx_closed.is_set()
                now = time.monotonic()
                self._heartbeat = now
                if not rx.queue and not closed:
                    deadline = min(next_pub if cfg.publish_interval > 0 else now + 0.25,
                                   self._info_due, next_ckpt, now + 0.25)
                    rx.wake.wait(max(0.0, deadline - now))
                    rx.wake.clear()
                if rx.queue and not closed and cfg.block_s > 0:
                    # let frames gather, but not past a publication: it carries them
                    until = last_block + cfg.block_s
                    if cfg.publish_interval > 0:
                        until = min(until, next_pub)
                    wait = until - time.monotonic()
                    if wait > 0 and not rx.hurry.is_set():
                        rx.hurry.wait(wait)  # a command or the end cuts it short
                rx.hurry.clear()
                if rx.queue:
                    last_block = time.monotonic()
                    self._drain(rx, closed)
                if self._reload_requested.is_set():
                    self._reload_requested.clear()
                    self._reload()
                now = time.monotonic()
                if cfg.publish_interval == 0 or now >= next_pub or self._publish_now:
                    self._publish_now = False
                    self._publish(now)
                    if cfg.publish_interval > 0:
                        next_pub = max(next_pub + cfg.publish_interval, now)
                if now >= next_ckpt:
                    self.checkpoint()
                    next_ckpt = now + cfg.checkpoint_interval
                self._est_cpu = time.thread_time() - cpu0
                if closed and not rx.queue:
                    break
        except Exception:  # pragma: no cover - must not die silently
            log.exception("estimator thread failed; stopping the daemon")
            self._stopping.set()
        finally:
            self._est_cpu = time.thread_time() - cpu0

    def _drain(self, rx: _RxListener, everything: bool) -> None:
        q = rx.queue
        pop = q.popleft
        while q:
            n = min(len(q), self.config.max_block)
            msgs = [pop() for _ in range(n)]
            rx.space.set()
            with self._lock:
                self._handle(msgs)
            if not everything:
                break

    def _handle(self, msgs: list[can.Message]) -> None:
        start = 0
        for i, m in enumerate(msgs):
            if m.is_error_frame:
                self._error_frame(m)
            elif m.arbitration_id == COMMAND_ID and not m.is_extended_id:
                self._process(msgs[start:i + 1])
                start = i + 1
                self._command(m)
        self._process(msgs[start:])

    def _process(self, msgs: list[can.Message]) -> None:
        if not msgs:
            return
        out = self._proc.process(messages_to_block(msgs))
        self._c["blocks"] += 1
        self._absorb(out)

    def _absorb(self, out: PipelineBlock) -> None:
        for k, eb in enumerate(out.equations):
            if len(eb.online_rms):
                self._online_rms[k] = float(eb.online_rms[-1])
            if len(eb.flags) and (eb.flags & _WINDUP).any():
                self._window_windup = True
        for e in self._proc.pipeline.estimators:
            if e.nonfinite_rows and e not in self._warned_nonfinite:
                self._warned_nonfinite.add(e)
                log.warning("the %s equation met a non-finite term value (a user term "
                            "outside its domain?): such samples, and the filter's warm-up "
                            "after each, are left out", e.equation.name)

    # ------------------------------------------------------------------ input gate
    def hold_input(self, hold: bool) -> None:
        """Stop (``True``) or restart taking frames from the bus listener.

        The notifier's thread waits while the input is held, so a simulated drive with
        ``realtime=False`` (frames made as they are read) pauses with it: the demo
        holds the drive while it computes the diagnosis. On a real bus frames would
        pile up in the interface's buffer: do not hold a live bus for long.
        """
        if hold:
            self._rx.gate.clear()
        else:
            self._rx.gate.set()

    # ------------------------------------------------------------------ model changes
    def _set_model(self, model: Model, why: str) -> None:
        self._proc.with_model(model)
        self._online_rms = [math.nan] * len(self._proc.pipeline.estimators)
        self._info_due = time.monotonic()  # tell monitors about the new parameters now
        self._publish_now = True
        log.info("%s: model is now %s (%d parameters; estimation restarts)", why,
                 ",".join(model.effect_names), len(model.parameters))

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
        with self._lock:
            self.config_model = new
            if new != self.model:
                self._set_model(new, "reload")
            else:
                log.info("reload: model unchanged (%s)", ",".join(new.effect_names))
        self.sd.ready()

    # ------------------------------------------------------------------ commands
    def _command(self, msg: can.Message) -> None:
        self._c["commands"] += 1
        code = msg.data[0] if len(msg.data) else 0
        try:
            cmd = decode_command(msg)
            code = int(cmd.code)
            if not self.config.commands:
                raise CommandFrameError("commands are disabled ([daemon] commands = false)",
                                        CommandResult.DISABLED, code)
            self._apply(cmd)
            result = CommandResult.OK
            log.info("command %s: ok", cmd)
        except CommandFrameError as e:
            result = e.result
            if e.code is not None:
                code = e.code
            self._c["commands_rejected"] += 1
            log.warning("command frame %s rejected (%s): %s", bytes(msg.data).hex(),
                        result.name.lower(), e)
        self._ack_counter = (self._ack_counter + 1) % 16
        self._send([encode_ack(code, result, self._ack_counter, timestamp=time.time())])

    def _apply(self, cmd: Command) -> None:
        """Apply a valid command; raise CommandFrameError (changing nothing) otherwise."""
        pipe = self._proc.pipeline
        c = cmd.code
        na = CommandResult.NOT_APPLICABLE
        if c is CommandCode.RESET:
            pipe.reset()
            self._online_rms = [math.nan] * len(pipe.estimators)
        elif c is CommandCode.FREEZE:
            if pipe.frozen:
                raise CommandFrameError("already frozen", na, int(c))
            pipe.freeze()
        elif c is CommandCode.RESUME:
            if not pipe.frozen:
                raise CommandFrameError("not frozen", na, int(c))
            pipe.resume()
        elif c is CommandCode.SET_LAMBDA:
            try:
                pipe.set_lambda(cmd.lam)
            except ConfigError as e:
                raise CommandFrameError(str(e), CommandResult.BAD_VALUE, int(c)) from e
        else:
            name = command_effect_name(cmd.effect, cmd.order, self.model)
            try:
                if c is CommandCode.ADD_EFFECT:
                    if name in self.model.effect_names:
                        raise CommandFrameError(f"effect {name} is already in the model", na,
                                                int(c))
                    model = self.model.with_effects(add=[name])
                else:
                    if name not in self.model.effect_names:
                        raise CommandFrameError(f"effect {name} is not in the model", na, int(c))
                    model = self.model.with_effects(remove=[name])
            except ConfigError as e:  # e.g. needs a signal the drive lacks, or no effect left
                raise CommandFrameError(str(e), na, int(c)) from e
            self._set_model(model, f"command {cmd}")

    # ------------------------------------------------------------------ publication
    #: (pipeline, its parameters as reports without estimates (a tuple per equation), its
    #: model's ActiveEffects): made again when the model changes, see _layout_of
    _layout: tuple[Pipeline | None, tuple[tuple[ParameterReport, ...], ...], int] = (None, (), 0)

    def _layout_of(self, pipe: Pipeline
                   ) -> tuple[Pipeline | None, tuple[tuple[ParameterReport, ...], ...], int]:
        """:attr:`_layout` for ``pipe``: what its parameters are, computed once per model."""
        layout = self._layout
        if layout[0] is not pipe:
            rows: list[tuple[ParameterReport, ...]] = []
            i = 0
            for e in pipe.estimators:
                params = e.equation.parameters
                rows.append(tuple(
                    ParameterReport(index=i + k, name=p.name, effect_id=EffectId(p.effect_id),
                                    component=p.component, order=p.order,
                                    equation=EquationId(p.equation_index), unit=p.unit)
                    for k, p in enumerate(params)))
                i += len(params)
            layout = (pipe, tuple(rows), pipe.model.active_effects)
            self._layout = layout
        return layout

    def _reports(self) -> tuple[list[ParameterReport], float]:
        """The parameters as published, and the largest float-vs-fixed divergence."""
        pipe = self._proc.pipeline
        out: list[ParameterReport] = []
        divs: list[float] = []
        for e, blanks in zip(pipe.estimators, self._layout_of(pipe)[1], strict=True):
            eq = e.equation
            th, sd, fx = e.rls.theta, e.rls.std(), e.frls.theta_float
            # as EquationEstimator.divergence (normalised units), from the same arrays
            divs.append(divergence(th.tolist(), fx.tolist(), sd.tolist()))
            value = eq.to_physical(th).tolist()
            sigma = eq.sigma_to_physical(sd).tolist()
            fixed = eq.to_physical(fx).tolist()
            valid = e.frls.count > 0
            out += [b.with_estimates(f, s, v, valid and math.isfinite(f))
                    for b, v, s, f in zip(blanks, value, sigma, fixed, strict=True)]
        return out, max(divs, default=0.0)

    def _wire_counters(self) -> dict[str, int]:
        d = self._proc.decoder
        b = self._base
        return {
            "frames_rejected": int(d.rejected.total) + b.get("frames_rejected", 0),
            "frames_lost": int(sum(d.lost.values())) + self._rx.overflow
            + b.get("frames_lost", 0),
            "saturations": int(self._proc.pipeline.saturations.total) + b.get("saturations", 0),
            "tx_dropped": self._c["tx_dropped"] + b.get("tx_dropped", 0),
        }

    def _bus_fault(self, now: float) -> bool:
        """Whether transmission is paused: an error frame less than ``fault_hold_s`` ago,
        or no usable bus."""
        return now < self._fault_until or self._failed.is_set() or self._bus is None

    def _settle_fault(self, now: float) -> None:
        """Estimator thread: once ``fault_hold_s`` passed without an error frame, the
        bus-off and fault states end (logged once)."""
        if self._bus_off and now >= self._fault_until:
            self._bus_off = False  # no error frame for fault_hold_s: recovered
        if self._fault_active and not self._bus_fault(now):
            self._fault_active = False
            log.info("CAN bus fault cleared: transmission resumed")

    def _status(self, now: float, div: float | None = None) -> StatusReport:
        """The status (no side effect: :meth:`status` calls it from any thread);
        ``div``: the divergence if known (:meth:`_reports`)."""
        pipe = self._proc.pipeline
        counters = self._wire_counters()
        lost = counters["frames_lost"]
        fault = self._bus_fault(now)
        if div is None:
            div = max((e.divergence() for e in pipe.estimators), default=0.0)
        first = pipe.estimators[0]
        return StatusReport(
            residual_rms=self._online_rms[0],
            update_count=int(first.rls.count),
            windup=self._window_windup,
            low_excitation=self._low_excitation,
            saturation=counters["saturations"] > self._last_sat,
            frame_loss=lost > self._last_lost,
            frozen=pipe.frozen,
            diverged=div > self.config.divergence_limit,
            bus_fault=fault,
            active_effects=self._layout_of(pipe)[2],
            divergence=div if math.isfinite(div) else 0.0,
            **counters)

    def _publish(self, now: float) -> None:
        """Send the parameter frames, then the status frames (and, every
        ``info_interval``, RlsParamInfo and RlsCounters)."""
        info = now >= self._info_due
        self._settle_fault(now)
        reports, div = self._reports()
        ts = time.time()
        self._pub_counter = (self._pub_counter + 1) % 16
        self._send(encode_parameters(reports, self._pub_counter, timestamp=ts))
        sent = time.monotonic()
        if info:
            self._low_excitation = any(bool(e.rls.excitation().low)
                                       for e in self._proc.pipeline.estimators)
        status = self._status(now, div)
        self._window_windup = False
        self._last_lost = status.frames_lost
        self._last_sat = status.saturations
        self.last_status = status
        msgs = [m for m in encode_status(status, self._pub_counter, timestamp=ts)
                if info or m.arbitration_id != _COUNTERS_ID]
        if info:
            msgs += encode_param_info(reports, timestamp=ts)
            self._info_due = now + self.config.info_interval
        self._send(msgs)
        self._c["publications"] += 1
        if self._on_publish is not None:
            self._on_publish(self._proc.frames, sent)
