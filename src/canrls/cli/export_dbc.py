"""``canrls export-dbc``: a DBC of canrls' own frames of every axis of a machine.

    canrls export-dbc --config machine.toml --out machine.dbc
    cantools monitor -c vcan0 machine.dbc

Each axis's parameter, status, command and acknowledgement frames on the IDs its daemon
uses (the shipped DBC's + the axis's ``own`` offset), named ``AXIS_MESSAGE``
(:mod:`canrls.can.axis_dbc`); without axes, the one drive's on ``[daemon] own_ids``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from canrls.cli._common import add_model_options, setup

__all__ = ["add_subparser", "run"]


def add_subparser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "export-dbc", help="write a DBC of canrls' own frames of every axis (cantools monitor)",
        description="Write a DBC with canrls' parameter, status, command and acknowledgement "
                    "frames of every axis of the configuration ([[axes]] or --axes) on the "
                    "IDs its daemon uses, each message named AXIS_MESSAGE, for cantools "
                    "monitor or any tool that reads a bus with a DBC (docs/daemon.md).")
    add_model_options(p)
    p.add_argument("--out", required=True, type=Path, metavar="FILE",
                   help="the DBC to write (to a temporary beside it, renamed when whole)")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from canrls.can.axis_dbc import axes_dbc
    from canrls.core.files import atomic_writer
    from canrls.processor.axes import own_offset

    cfg = setup(args, every_axis=True)
    if cfg.axes:
        # every axis's protocol built and its own frames checked, as a start does
        configs = cfg.axis_configs()
        offsets = {n: own_offset(c.daemon["own_ids"], f"axis {n}: own")
                   for n, c in configs.items()}
        if cfg.axis_name is not None:
            if cfg.axis_name not in offsets:
                cfg.one_axis()  # the error naming the axes
            offsets = {cfg.axis_name: offsets[cfg.axis_name]}
    else:
        v = cfg.daemon.get("own_ids")
        offsets = {"": 0 if v is None else own_offset(v, f"{cfg.source}: daemon.own_ids")}
    text = axes_dbc(offsets)
    with atomic_writer(args.out, f"--out {args.out}") as f:
        f.write(text.encode("utf-8"))
    names = ", ".join(n for n in offsets if n) or "one drive"
    print(f"{args.out}: canrls' own frames of {names} "
          f"({text.count(chr(10) + 'BO_ ')} messages)")
    return 0
