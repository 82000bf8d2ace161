"""``canrls run``: the daemon, live on a CAN bus.

    canrls run --config /etc/canrls/canrls.toml            # [can] interface/channel/bitrate
    canrls run -i socketcan -c can0 --effects inertia,viscous,coulomb --kt 0.1
    canrls run -i canrls-sim -c standard --bus-kwargs seed=1 --duration 10 --json

Reads the drive's feedback frames, runs the same pipeline as ``canrls fit`` (float and
fixed-point RLS side by side), publishes parameter and status frames, answers command
frames, checkpoints, and talks to systemd (``Type=notify``, watchdog). SIGTERM/SIGINT
stop it (with a final checkpoint), SIGHUP re-reads the configuration's model. On exit
it prints the final estimates (``--json``: one object with the estimates and the
daemon's counters). Logging goes to stderr (journald under systemd).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from canrls.cli._common import add_bus_options, add_model_options, print_json, setup
from canrls.errors import ConfigError

__all__ = ["add_subparser", "run", "build_daemon"]


def add_subparser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "run", help="run the estimator live on a CAN bus (the daemon)",
        description="Identify the drive's parameters live: read feedback frames from a CAN "
                    "bus, publish estimates and status, answer commands (see docs/daemon.md).")
    add_model_options(p)
    add_bus_options(p)
    g = p.add_argument_group("daemon (each also settable in [daemon] of --config)")
    g.add_argument("--checkpoint", metavar="FILE", help="checkpoint file (resumed at start)")
    g.add_argument("--checkpoint-interval", type=float, metavar="S",
                   help="seconds between checkpoints (default 60)")
    g.add_argument("--publish-interval", type=float, metavar="S",
                   help="seconds between parameter publications (default 0.1; frames are "
                        "processed in blocks as often, unless [daemon] block_interval is set)")
    g.add_argument("--no-commands", action="store_true",
                   help="answer every command frame with 'disabled'")
    g.add_argument("--record", metavar="LOG", help="write every received frame to LOG")
    g.add_argument("--duration", type=float, metavar="S",
                   help="stop after S seconds (default: until SIGTERM/SIGINT)")
    p.set_defaults(func=run)
    return p


def _daemon_table(cfg: Any, args: argparse.Namespace) -> dict[str, Any]:
    table = dict(cfg.daemon)
    for opt, key in (("checkpoint", "checkpoint"), ("record", "record")):
        v = getattr(args, opt, None)
        if v:
            table[key] = str(Path(v).absolute())  # not resolved: a link stays a link
    for opt, key in (("checkpoint_interval", "checkpoint_interval"),
                     ("publish_interval", "publish_interval")):
        v = getattr(args, opt, None)
        if v is not None:
            table[key] = v
    if getattr(args, "no_commands", False):
        table["commands"] = False
    return table


def build_daemon(args: argparse.Namespace) -> Any:
    """The :class:`~canrls.live.daemon.Daemon` the command line describes (not started)."""
    from canrls.config import load_config, read_toml
    from canrls.estimation.model import Model
    from canrls.live.bus import bus_config
    from canrls.live.daemon import Daemon, DaemonSettings

    cfg = setup(args)
    dset = DaemonSettings.from_table(_daemon_table(cfg, args), cfg.source, cfg.base_dir)
    protocol = cfg.protocol()

    def configured_model() -> Model:
        c = load_config(getattr(args, "config", None), args)
        if dset.model_file is not None:
            c.model = read_toml(dset.model_file, "model", key="daemon.model_file")
            c.apply_args(args)
        return c.model_for(protocol)

    model = configured_model()
    return Daemon(protocol, model, cfg.settings(), dset, bus=bus_config(cfg, args),
                  reload=configured_model)


def run(args: argparse.Namespace) -> int:
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise ConfigError(f"--duration: {args.duration!r} must be a positive number of seconds")
    daemon = build_daemon(args)
    daemon.run(duration=args.duration)
    est = daemon.estimates()
    if args.json:
        d = est.to_dict()
        d["daemon"] = daemon.stats().to_dict()
        st = daemon.last_status
        d["status"] = None if st is None else {
            "residual_rms": st.residual_rms, "update_count": st.update_count,
            "flags": list(st.flags), "active_effects": st.active_effects}
        print_json(d)
    else:
        sys.stdout.write(est.format() + "\n")
    return 0
