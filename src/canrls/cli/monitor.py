"""``canrls monitor``: a live view of a running daemon, from any python-can interface.

    canrls monitor -i socketcan -c can0 --config canrls.toml
    canrls monitor -i remote -c ws://127.0.0.1:54701/ --once --json
    canrls monitor -i socketcan -c can0 --command "add cogging:6"

On a terminal the view is redrawn in place every ``--interval`` seconds (plain ANSI
cursor-home and clear-to-end sequences: no curses, no extra dependency); otherwise
(a pipe, a log, journald) a plain-text block is printed each interval. ``--once``
waits for one complete publication (every parameter and a status), prints it and
exits (status 1 if none came within ``--timeout``); ``--duration S`` stops after S
seconds. ``--command`` sends an ``RlsCommand`` (``reset``, ``freeze``, ``resume``,
``add EFFECT``, ``remove EFFECT``, ``lambda L``) and prints the acknowledgement.
Units come from the effect library with the axis, ``kt`` and user terms of
``--config``/``--kt`` (the daemon's model).
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

from canrls.cli._common import add_bus_options, add_model_options, print_json, setup
from canrls.core.checks import is_positive
from canrls.core.errors import ConfigError

__all__ = ["add_subparser", "run"]

#: the view's options when neither the command line nor ``[monitor]`` sets them
_VIEW_DEFAULTS: dict[str, Any] = {"interval": 1.0, "timeout": 10.0, "plain": False}

#: end of a line on the terminal: clear what an older, longer line left, then newline
_EOL = "\x1b[K\n"


def add_subparser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "monitor", help="live view of the daemon's parameter and status frames",
        description="Show every parameter the daemon publishes (fixed, ±σ, float, unit), the "
                    "residual RMS and its trend, frame rates, counters, rejected frames by "
                    "reason (RlsRejects: CRC, counters, range, unpaired, reordered, clock "
                    "steps and gaps; RlsHealth: receive times) and health flags "
                    "(ClockFault among them).")
    add_model_options(p)
    add_bus_options(p)
    g = p.add_argument_group("view")
    g.add_argument("--once", action="store_true",
                   help="print one complete view and exit")
    g.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    g.add_argument("--interval", type=float, metavar="S",
                   help="seconds between refreshes (default: [monitor] interval, else 1)")
    g.add_argument("--timeout", type=float, metavar="S",
                   help="--once/--command: give up after S seconds; the continuous view "
                        "on a bus of its own (virtual, canrls-sim) says after S seconds why "
                        "nothing comes (default: [monitor] timeout, else 10)")
    g.add_argument("--plain", action="store_true", default=None,
                   help="plain text even on a terminal (no redraw, no colour; default: "
                        "[monitor] plain)")
    g.add_argument("--command", action="append", default=[], metavar="CMD",
                   help="send a command first: reset, freeze, resume, 'add EFFECT', "
                        "'remove EFFECT', 'lambda L', save (the running model to [daemon] "
                        "saved_model, for canrls tune) (repeatable)")
    p.set_defaults(func=run)
    return p


def _positive(name: str, v: float | None) -> None:
    if v is not None and not is_positive(v):
        raise ConfigError(f"{name}: {v!r} must be a positive number of seconds")


def run(args: argparse.Namespace) -> int:
    import can

    from canrls.can.estimator_frames import encode_command, frame_ids
    from canrls.live.bus_link import bus_config, moved, open_bus
    from canrls.live.daemon_settings import DaemonSettings
    from canrls.live.monitor_listener import LibraryUnits, Monitor, parse_command_text
    from canrls.processor.config import prepare

    for name in ("duration", "interval", "timeout"):
        _positive(f"--{name}", getattr(args, name))
    commands = [parse_command_text(c) for c in args.command]
    cfg = setup(args, every_axis=True)
    for name in ("interval", "timeout", "plain"):  # [monitor] under the flags
        if getattr(args, name) is None:
            setattr(args, name, cfg.monitor.get(name, _VIEW_DEFAULTS[name]))
    if len(cfg.axes) > 1 and cfg.axis_name is None:
        return _run_axes(args, cfg)
    cfg = cfg.one_axis()
    try:
        protocol, model, _ = prepare(cfg)
        units = LibraryUnits.for_model(model)
        feedback = [m.frame_id for m in protocol.messages]
        user_names = list(model.terms)
    except ConfigError:
        if cfg.model or cfg.signals or cfg.can.get("dbc"):
            raise
        units, feedback, user_names = LibraryUnits(), list(frame_ids().feedback), []
    conf = bus_config(cfg)
    tty = sys.stdout.isatty() and not args.plain and not args.json
    own = DaemonSettings.from_config(cfg).own_offset  # an axis's own frames
    mon = Monitor(units=units, user_names=user_names, feedback_ids=feedback,
                  source=f"{conf.get('interface')}:{conf.get('channel')}", own_offset=own)
    bus = open_bus(conf)
    status = 0
    try:
        with can.Notifier(bus, [mon], timeout=0.1):
            for text, (code, eid, order, lam) in zip(args.command, commands, strict=True):
                before = len(mon.acks)
                bus.send(moved(encode_command(code, eid, order, lam), own), timeout=1.0)
                ack = mon.wait_ack(before, args.timeout)
                if ack is None:
                    print(f"error: no acknowledgement of {text!r} within "
                          f"{args.timeout:g} s{_own_bus_hint(conf)}", file=sys.stderr)
                    return 1
                print(f"{code.name.lower()}: {ack.result.name.lower()}")
                if ack.result:
                    status = 1
            if commands and not (args.once or args.duration):
                return status
            status = max(status, _watch(args, mon, tty, _own_bus_hint(conf)))
    finally:
        bus.shutdown()
    return status


def _run_axes(args: argparse.Namespace, cfg: Any) -> int:
    """``canrls monitor`` of a machine without ``--axis``: one row per axis."""
    import can

    from canrls.live.bus_link import bus_config, open_bus
    from canrls.live.daemon_settings import DaemonSettings
    from canrls.live.monitor_listener import AxesMonitor, LibraryUnits, Monitor
    from canrls.processor.config import prepare

    if args.command:
        raise ConfigError("--command: a command reaches one axis: give --axis NAME")
    conf = bus_config(cfg)
    source = f"{conf.get('interface')}:{conf.get('channel')}"
    monitors = {}
    for name, c in cfg.axis_configs().items():
        protocol, model, _ = prepare(c)
        monitors[name] = Monitor(
            units=LibraryUnits.for_model(model), user_names=list(model.terms),
            feedback_ids=[m.frame_id for m in protocol.messages], source=source,
            own_offset=DaemonSettings.from_config(c).own_offset)
    mon = AxesMonitor(monitors)
    tty = sys.stdout.isatty() and not args.plain and not args.json
    bus = open_bus(conf)
    try:
        with can.Notifier(bus, list(monitors.values()), timeout=0.1):
            return _watch(args, mon, tty, _own_bus_hint(conf))
    finally:
        bus.shutdown()


#: interfaces whose bus lives inside one process (python-can's virtual bus, and the
#: simulated drive on one): a daemon in another process is never on it
_IN_PROCESS = ("virtual", "canrls-sim")


def _own_bus_hint(conf: dict[str, Any]) -> str:
    """Why nothing came, when the bus is the process's own; else nothing."""
    if conf.get("interface") not in _IN_PROCESS:
        return ""
    return (f": each process gets its own {conf.get('interface')} bus, so a daemon in "
            f"another process is not on it; share one bus with python-can-remote on "
            f"127.0.0.1 (python -m can_remote -i canrls-sim -c standard -H 127.0.0.1 -p "
            f"54701, then canrls run and canrls monitor with -i remote -c "
            f"ws://127.0.0.1:54701/; docs/daemon.md, Remote), or run canrls demo (drive, "
            f"daemon and monitor in one process)")


def _watch(args: argparse.Namespace, mon: Any, tty: bool, hint: str = "") -> int:
    """The views until ``--duration`` (or one with ``--once``); ``hint``: why nothing
    comes on a bus of the process's own (:func:`_own_bus_hint`), said after
    ``--timeout`` seconds without a complete publication."""
    start = time.monotonic()
    end = None if args.duration is None else start + args.duration
    nothing = f"no complete publication from a canrls daemon within {args.timeout:g} s " \
              f"on {mon.source}"
    if args.once:
        deadline = start + args.timeout
        while time.monotonic() < deadline:
            view = mon.snapshot()
            if view.complete:
                time.sleep(min(0.3, max(0.0, deadline - time.monotonic())))  # rates settle
                _emit(args, mon.snapshot(), tty=False)
                return 0
            if mon.error is not None:
                break
            time.sleep(0.05)
        print(f"error: {nothing}" + (f" ({mon.error})" if mon.error else hint),
              file=sys.stderr)
        return 1
    said = False
    try:
        while end is None or time.monotonic() < end:
            nxt = time.monotonic() + args.interval
            if end is not None:
                nxt = min(nxt, end)
            time.sleep(max(0.0, nxt - time.monotonic()))
            view = mon.snapshot()
            # a bus of its own never carries a daemon: said under each redrawn view, or
            # once on stderr beside the printed ones
            note = bool(hint) and not view.complete and time.monotonic() - start >= args.timeout
            _emit(args, view, tty, f"canrls monitor: {nothing}{hint}" if note and tty else "")
            if note and not tty and not said:
                print(f"canrls monitor: {nothing}{hint}", file=sys.stderr)
                said = True
            if mon.error is not None:
                print(f"error: bus failed: {mon.error}", file=sys.stderr)
                return 1
    except KeyboardInterrupt:
        pass
    return 0


def _emit(args: argparse.Namespace, view: Any, tty: bool, note: str = "") -> None:
    """One view on stdout (``note``: a line under the redrawn view)."""
    if args.json:
        print_json(view.to_dict())
    elif tty:
        # cursor home, every line cleared to its end, then the rest of the screen: the
        # view is redrawn in place without the flicker of clearing the screen first
        text = (view.format(color=True) + (f"\n\n{note}" if note else "")).replace("\n", _EOL)
        sys.stdout.write(f"\x1b[H{text}{_EOL}\x1b[J")
    else:
        sys.stdout.write(view.format() + "\n\n")
    sys.stdout.flush()
