"""``canrls run``: the daemon, live on a CAN bus.

    canrls run --config /etc/canrls/canrls.toml            # [can] interface/channel/bitrate
    canrls run -i socketcan -c can0 --effects inertia,viscous,coulomb --kt 0.1
    canrls run -i canrls-sim -c standard --bus-kwargs seed=1 --duration 10 --json

Reads the drive's feedback frames, runs the same pipeline as ``canrls fit`` (float and
fixed-point RLS side by side), publishes parameter and status frames, answers command
frames (only with ``--commands`` or ``[daemon] commands = true``; otherwise each is
answered ``disabled``), checkpoints, and talks to systemd (``Type=notify``, watchdog).
SIGTERM/SIGINT stop it (with a final checkpoint; a second one while it stops changes
nothing), SIGHUP re-reads the configuration: the model applies at once, the rest at the
next start (said in the log); a file a start would refuse is refused. On exit it prints the final
estimates (``--json``: one object with the estimates, the daemon's counters, the frames
rejected by reason as ``canrls fit --json`` has them, and the last status). A machine's
axes (``--axes`` or ``[[axes]]``, no ``--axis NAME``) run one daemon each, reported
under ``== axis NAME ==`` (``--json``: ``{"axes": {NAME: ...}}``); the configuration
is read once at start and once per SIGHUP for all of them (:class:`Configuration`),
``[history]`` storing each axis as the drive ``DRIVE.AXIS``. In text mode the
journal's lines (publishing, model changes, faults) go to stdout; logging goes to
stderr (journald under systemd).

Exit status: 0 after a requested stop (SIGTERM, SIGINT, ``--duration``), however many
signals arrive; 1 for an error (one ``error:`` line on stderr): a bad configuration, a
bus that cannot be opened, or an exception that ended the estimator or supervisor
thread (logged with its traceback) -- so systemd's ``Restart=on-failure`` restarts it.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from canrls.cli import early_signals
from canrls.cli._common import (
    add_bus_options,
    add_model_options,
    overrides,
    print_json,
)
from canrls.core.checks import is_positive
from canrls.core.errors import ConfigError
from canrls.live.signals import SignalRelay

if TYPE_CHECKING:
    from canrls.can.protocol import Protocol
    from canrls.estimation.model import Model
    from canrls.estimation.settings import EstimatorSettings
    from canrls.live.daemon import Daemon
    from canrls.live.daemon_settings import DaemonSettings

__all__ = ["add_subparser", "run", "build_daemon", "daemon_for", "fixed_path_for"]


def add_subparser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "run", help="run the estimator live on a CAN bus (the daemon)",
        description="Identify the drive's parameters live: read feedback frames from a CAN "
                    "bus, publish estimates and status, answer commands (off unless "
                    "--commands; see docs/daemon.md). Exit status: 0 after a requested stop "
                    "(SIGTERM, SIGINT, --duration; a second SIGTERM changes nothing), 1 on "
                    "an error (configuration, bus, or an internal error of the daemon).")
    add_model_options(p)
    add_bus_options(p)
    g = p.add_argument_group("daemon (each also settable in [daemon] of --config)")
    g.add_argument("--checkpoint", metavar="FILE", help="checkpoint file (resumed at start)")
    g.add_argument("--checkpoint-interval", type=float, metavar="S",
                   help="seconds between checkpoints (default 60)")
    g.add_argument("--publish-interval", type=float, metavar="S",
                   help="seconds between parameter publications (default 0.1; frames are "
                        "processed in blocks as often, unless [daemon] block_interval is set)")
    cmds = g.add_mutually_exclusive_group()
    cmds.add_argument("--commands", dest="commands", action="store_true", default=None,
                      help="accept RlsCommand frames (default: off, every command frame is "
                           "answered 'disabled'; bounded by [daemon] max_parameters, "
                           "command_rate, command_burst)")
    cmds.add_argument("--no-commands", dest="commands", action="store_false",
                      help="answer every command frame with 'disabled' (the default, "
                           "unless [daemon] commands = true)")
    g.add_argument("--record", metavar="LOG", help="write every received frame to LOG")
    g.add_argument("--duration", type=float, metavar="S",
                   help="stop after S seconds (default: until SIGTERM/SIGINT)")
    p.set_defaults(func=run)
    return p


def _daemon_table(cfg: Any, args: argparse.Namespace) -> dict[str, Any]:
    from canrls.can.writers import check_record_path

    table = dict(cfg.daemon)
    for opt, key in (("checkpoint", "checkpoint"), ("record", "record")):
        v = getattr(args, opt, None)
        if v:
            if opt == "record":  # its format and place, named as typed
                check_record_path(v, f"--record {v}")
            table[key] = str(Path(v).absolute())  # not resolved: a link stays a link
    for opt, key in (("checkpoint_interval", "checkpoint_interval"),
                     ("publish_interval", "publish_interval")):
        v = getattr(args, opt, None)
        if v is not None:
            table[key] = v
    if getattr(args, "commands", None) is not None:
        table["commands"] = args.commands
    return table


def _per_axis(table: dict[str, Any], axis: str) -> dict[str, Any]:
    """``table`` with its files made the axis's own (``ckpt.bin`` -> ``ckpt.NAME.bin``):
    each axis of a machine checkpoints, records and saves on its own."""
    out = dict(table)
    for key in ("checkpoint", "record", "saved_model"):
        if out.get(key):
            p = Path(out[key])
            out[key] = str(p.with_name(f"{p.stem}.{axis}{p.suffix}"))
    return out


class Configuration:
    """The configuration ``canrls run`` serves: read once at start and once per SIGHUP
    (:meth:`reread`); every axis's daemon takes its own from it (:meth:`axis`).

    :param nodes: the :class:`~canrls.can.eds.NodeReader` an EDS drive's values are read
        with on the bus (None: the EDS's defaults).
    """

    def __init__(self, args: argparse.Namespace, nodes: Any = None) -> None:
        self.args = args
        self.over = overrides(args)
        self.nodes = nodes
        self.machine = self._read()

    def _read(self) -> Any:
        from canrls.processor.config import load_config

        c = load_config(getattr(self.args, "config", None), self.over)
        c.nodes = self.nodes
        return c

    def reread(self) -> Any:
        """Read the file again (a :class:`ConfigError` keeps the last one); the machine's."""
        self.machine = self._read()
        return self.machine

    def axis(self, name: str | None) -> Any:
        """The configuration of axis ``name`` (None: of the one axis) as last read."""
        c = self.machine.one_axis() if name is None else self.machine.axis(name)
        return dataclasses.replace(c, model=dict(c.model))  # [daemon] model_file: its own

    def history(self, cfg: Any, name: str | None) -> Any:
        """``[history]`` of axis ``name``'s configuration ``cfg`` checked: its settings,
        the drive ``DRIVE.AXIS`` for an axis of ``[[axes]]`` or ``--axes`` (also the one
        ``--axis NAME`` picks, or the only one), as ``canrls fleet ingest`` stores a
        machine's logs; None without the table."""
        if not cfg.history:
            return None
        from canrls.fleet.live_appender import HistorySettings

        settings = HistorySettings.from_table(cfg.history, cfg.source)
        if name is None and self.machine.axes:  # the axis --axis picks, or the only one
            name = self.machine.axis_name or self.machine.axis_specs()[0].name
        if name is None:
            return settings
        from canrls.fleet.sources import check_name

        drive = check_name(f"{settings.drive}.{name}", "drive", f"{cfg.source}: history")
        return dataclasses.replace(settings, drive=drive)


def build_daemon(args: argparse.Namespace, axis: str | None = None,
                 nodes: Any = None, current: Configuration | None = None) -> Any:
    """The :class:`~canrls.live.daemon.Daemon` the command line describes (not started);
    of the machine's axis ``axis`` (its files its own), else of the one axis. ``current``:
    the configuration as read (None: read here). On SIGHUP the one axis reads the file
    again; a machine's axis takes what the machine read, once for all its axes."""
    from canrls.live.bus_link import bus_config
    from canrls.live.daemon_settings import DaemonSettings
    from canrls.processor.config import AppConfig, prepare, read_toml

    own_reads = axis is None  # a machine's axis: the machine reads the file on SIGHUP
    conf = Configuration(args, nodes) if current is None else current

    def table(c: AppConfig) -> dict[str, Any]:
        t = _daemon_table(c, args)
        return t if axis is None else _per_axis(t, axis)

    cfg = conf.axis(axis)
    dset = DaemonSettings.from_table(table(cfg), cfg.source, cfg.base_dir)
    if axis is not None and dset.record is None:  # a machine's axis: its own frames only
        dset = dataclasses.replace(dset, rx_filter=True)
    model_over = dataclasses.replace(conf.over, axes=None, axis_name=None, groups=())

    def with_model_file(c: AppConfig) -> AppConfig:
        """``c`` with ``[daemon] model_file``'s model (the command line still over it)."""
        if dset.model_file is not None:
            c.model = read_toml(dset.model_file, "model", key="daemon.model_file")
            c.apply(model_over)
        return c

    hist = conf.history(cfg, axis)
    key = None
    if hist is not None:  # the fleet's code only for a [history]
        from canrls.fleet.ingest import model_key_of

        key = model_key_of(cfg)
    protocol, model, settings = prepare(with_model_file(cfg))
    from canrls.processor.axes import check_own

    # a drive frame on one of canrls' own IDs: the daemon would take its own
    # publications (or a command) as the drive's
    check_own({"the drive": protocol}, {"the drive": dset.own_offset}, _OWN_HINT)
    bus = bus_config(cfg)

    def reloaded_model() -> Any:
        """SIGHUP: the model again, from a file a start would accept (the whole
        configuration is prepared as at a start: a DBC that does not exist, a mapping,
        a ``[daemon]`` or ``[history]`` table a restart would refuse is said at once, and
        the reload refused, the running configuration kept). What else changed (the DBC,
        the mapping, the bus, ``[estimator]``, ``[fixed]``, ``[daemon]``, ``[history]``)
        is logged: it applies at the next start; the model applies now."""
        try:
            if own_reads:
                conf.reread()
            c = conf.axis(axis)
            new = DaemonSettings.from_table(table(c), c.source, c.base_dir)
            new_hist = conf.history(c, axis)
            new_protocol, _, new_settings = prepare(with_model_file(c))
            new_bus = bus_config(c)
            reloaded = c.model_for(protocol)  # the model on the frames being decoded
        except ConfigError as e:
            raise ConfigError(f"{e}; the running daemon keeps its configuration (a restart "
                              f"would refuse this file)") from e
        changed = protocol.changes(new_protocol)
        changed += ["the bus"] if new_bus != bus else []
        changed += ["[estimator] or [fixed]"] if new_settings != settings else []
        changed += [f"[daemon] {f.name}" for f in dataclasses.fields(new)
                    if getattr(new, f.name) != getattr(dset, f.name)]
        changed += ["[history]"] if new_hist != hist else []
        if changed:
            log.warning("reload: %s%s changed: applied at the next start, not now",
                        "" if axis is None else f"axis {axis}: ", ", ".join(changed))
        return reloaded

    history = None if hist is None or key is None else _history_hook(hist, key)
    try:
        return daemon_for(protocol, model, settings, dset, bus=bus,
                          reload=reloaded_model, history=history, configuration=cfg)
    except BaseException:
        if history is not None:
            history.close()
        raise


def daemon_for(protocol: Protocol, model: Model, settings: EstimatorSettings,
               dset: DaemonSettings, **kwargs: Any) -> Daemon:
    """A daemon built as ``canrls run`` builds it (not started): its published fixed column
    from where ``[daemon] fixed`` says (:func:`fixed_path_for`); ``kwargs`` (the bus, the
    hooks) go to :class:`~canrls.live.daemon.Daemon` as they are. The benchmarks and the
    soak under tools/ build theirs here, so that they measure the daemon users run."""
    from canrls.live.daemon import Daemon

    return Daemon(protocol, model, settings, dset,
                  fixed_path=fixed_path_for(protocol, settings, dset), **kwargs)


def fixed_path_for(protocol: Protocol, settings: EstimatorSettings,
                   dset: DaemonSettings) -> Any:
    """Where a daemon's published fixed column comes from, as ``[daemon] fixed`` says:
    the target's integer path (``"target"``), or None, the kernel on the float front end."""
    if dset.fixed != "target":
        return None
    from canrls.firmware.target_live import LiveTarget

    return LiveTarget(protocol, settings)


def _history_hook(settings: Any, key: tuple[str, str]) -> Any:
    """``[history]``: the fleet history the daemon appends its parameters to (its
    :class:`~canrls.fleet.live_appender.HistorySettings`), under the model ``key`` (key and
    description, :func:`~canrls.fleet.ingest.model_key_of`)."""
    from canrls.fleet.live_appender import LiveAppender
    from canrls.live.history_hook import HistoryHook

    appender = LiveAppender.open(settings, *key)
    return HistoryHook(appender.append, settings.interval, close=appender.close)


log = logging.getLogger(__name__)

_STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)
#: what a drive frame on one of canrls' own IDs asks for
_OWN_HINT = ("give the drive's message another ID, or move canrls' frames with [daemon] "
             "own_ids = \"offset:N\"")


class _Stop:
    """What a SIGTERM/SIGINT stops: remembered until the daemon exists, then its
    :meth:`request_stop` (called from the signal relay's thread, under a lock that only
    threads take, never a signal handler)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._daemon: Any = None
        self._requested = False

    def signal(self, signum: int) -> None:
        with self._lock:
            self._requested = True
            d = self._daemon
        if d is not None:
            d.request_stop()
        log.info("signal %d: stopping", signum)

    def attach(self, daemon: Any) -> None:
        """``daemon`` now exists: a stop requested before is passed on (its run then
        starts, sees the request and stops cleanly)."""
        with self._lock:
            self._daemon = daemon
            requested = self._requested
        if requested:
            daemon.request_stop()


@contextmanager
def _signals_for_life(stop: _Stop, process_exits: bool) -> Iterator[None]:
    """SIGTERM/SIGINT/SIGHUP for the whole command, not only while the daemon serves.

    Before the daemon exists a stop is remembered (:class:`_Stop`) and a SIGHUP ignored;
    while it runs, :meth:`Daemon.run` has its own handlers; after it stopped, further
    signals only log. At the end, when the command is the process's own
    (``process_exits``), SIGTERM, SIGINT and SIGHUP are left ignored if they had their
    default action or Python's (the process is exiting: a late SIGTERM or SIGINT must not
    turn a clean stop into death by signal, exit status -15 or -2, or 130; a Python
    handler would not do, Python resets it to the default while it finalises);
    otherwise the handlers are restored: ``SIG_IGN`` passes to every process started
    afterwards.
    """
    def hup(signum: int) -> None:
        log.info("SIGHUP: nothing to reload now")

    relay = SignalRelay({**{sig: stop.signal for sig in _STOP_SIGNALS}, signal.SIGHUP: hup})
    with relay:
        old = {**relay.previous, **early_signals.previous_handlers()}  # before main's
        early = early_signals.stop_requested()
        if early is not None:  # before these handlers, even before the imports
            stop.signal(early)
        try:
            yield
        finally:
            for sig, h in old.items():
                # Python's own SIGINT handler raises KeyboardInterrupt: exit status 130
                quiet = process_exits and h in (signal.SIG_DFL, signal.default_int_handler)
                relay.leave(sig, signal.SIG_IGN if quiet else h)


def run(args: argparse.Namespace) -> int:
    from canrls.live.journal import JOURNAL, to_stream

    if args.duration is not None and not is_positive(args.duration):
        raise ConfigError(f"--duration: {args.duration!r} must be a positive number of seconds")
    stop = _Stop()
    with _signals_for_life(stop, getattr(args, "process_exits", False)):
        daemon, said = _build(args)
        stop.attach(daemon)
        with contextlib.nullcontext() if args.json else to_stream(sys.stdout):
            for line in said:
                JOURNAL.info("%s", line)
            status = daemon.run(duration=args.duration)
        if hasattr(daemon, "daemons"):
            _report_machine(daemon, args)
        else:
            _report(daemon, args)
    if daemon.failure is not None:
        print(f"error: the daemon stopped on an internal error: "
              f"{type(daemon.failure).__name__}: {daemon.failure}", file=sys.stderr)
    return status


def _node_reader(cfg: Any) -> Any:
    """With an EDS (``--eds``), what reads its nodes' mapping and ratings over SDO on
    the bus the daemon opens (another handle of it, closed after each upload)."""
    if cfg.can.get("eds") is None:
        return None
    from canrls.can.eds import NodeReader
    from canrls.live.bus_link import bus_config, open_bus

    conf = bus_config(cfg)
    return NodeReader(lambda: open_bus(conf))


def _said(nodes: Any) -> list[str]:
    """What the node reader said of each node's values (the journal's first lines)."""
    return [] if nodes is None else [x for n in sorted(nodes.said) for x in nodes.said[n]]


def _build(args: argparse.Namespace) -> tuple[Any, list[str]]:
    """The daemon of one axis, or of every axis of a machine (no ``--axis``): each axis
    its own :class:`~canrls.live.daemon.Daemon` in one
    :class:`~canrls.live.machine_daemon.MachineDaemon`, the whole machine checked first; and
    where an EDS drive's values came from (:func:`_said`). The configuration is read
    once here, and once per SIGHUP."""
    conf = Configuration(args)
    nodes = conf.nodes = conf.machine.nodes = _node_reader(conf.machine)
    try:
        return _build_axes(args, conf), _said(nodes)
    finally:
        if nodes is not None:
            nodes.close()


def _build_axes(args: argparse.Namespace, conf: Configuration) -> Any:
    cfg = conf.machine
    if len(cfg.axes) < 2 or cfg.axis_name is not None:
        return build_daemon(args, current=conf)
    from canrls.live.machine_daemon import MachineDaemon

    names = list(cfg.axis_configs())
    daemons: dict[str, Any] = {}
    try:
        for name in names:
            daemons[name] = build_daemon(args, name, current=conf)
    except BaseException:
        for d in daemons.values():
            d.stop()
        raise

    def build(name: str) -> Any:
        try:
            return build_daemon(args, name, current=conf)
        finally:
            if conf.nodes is not None:
                conf.nodes.close()

    def axes() -> list[str]:
        """SIGHUP: the file read again, once for the machine; its axes, each checked
        as at a start (its ``[history]`` too)."""
        names = list(conf.reread().axis_configs())
        for n in names:
            conf.history(conf.axis(n), n)
        return names

    return MachineDaemon(daemons, build=build, axes=axes)


def _report_machine(machine: Any, args: argparse.Namespace) -> None:
    """Every axis's final estimates: ``{"axes": {NAME: as one axis's --json}}``, or a
    first line with the axes and each axis's estimates under ``== axis NAME ==``."""
    if args.json:
        print_json({"axes": {n: _axis_dict(d) for n, d in machine.daemons.items()}})
        return
    lines = [f"{len(machine.daemons)} axes: " + ", ".join(
        f"{n} {d.stats().frames} frames" for n, d in machine.daemons.items())]
    for n, d in machine.daemons.items():
        lines += ["", f"== axis {n} ==", d.estimates().format()]
    sys.stdout.write("\n".join(lines) + "\n")


def _report(daemon: Any, args: argparse.Namespace) -> None:
    """The final estimates on stdout (``--json``: with the daemon's counters)."""
    if args.json:
        print_json(_axis_dict(daemon))
    else:
        sys.stdout.write(daemon.estimates().format() + "\n")


def _axis_dict(daemon: Any) -> dict[str, Any]:
    """One daemon's estimates, counters, frames and last status (``--json``)."""
    d = daemon.estimates().to_dict()
    d["daemon"] = daemon.stats().to_dict()
    d["frames"] = daemon.frame_counts()  # as canrls fit --json: rejected by reason
    st = daemon.last_status
    d["status"] = None if st is None else {
        "residual_rms": st.residual_rms, "update_count": st.update_count,
        "flags": list(st.flags), "active_effects": st.active_effects,
        "rejects": dict(st.rejects)}
    return d
