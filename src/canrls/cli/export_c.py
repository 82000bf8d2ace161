"""``canrls export-c``: the C code of a model for the target.

Writes into ``--out`` the fixed-point RLS kernel (``canrls_fixed.h/.c``), the
configuration of the model's equations (``canrls_config.h/.c``: parameters, scaling, Q
formats, the kernel's plan and prior) and cantools' C codecs of canrls' parameter and
command frames (``canrls_frames.h/.c``); see :mod:`canrls.c_export`. ``--model`` is a
TOML configuration or a saved model (``canrls fit --save-model``).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

__all__ = ["add_subparser", "run"]


def add_subparser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "export-c", help="write the C kernel, the model's configuration and the frame codecs",
        description="Write a directory that compiles for the target: the fixed-point RLS "
                    "kernel, the configuration header of the model (effects, scaling, Q "
                    "formats, plan) and the C codecs of canrls' frames from the DBC.")
    p.add_argument("--model", required=True, metavar="FILE",
                   help="TOML configuration, or a saved model (.json, canrls fit "
                        "--save-model)")
    p.add_argument("--out", type=Path, default=Path("canrls_c"), metavar="DIR",
                   help="output directory, made if missing (default: canrls_c); each file "
                        "is written to a temporary beside it and renamed")
    p.add_argument("--dt", type=float, default=None, metavar="S",
                   help="control period in seconds (default: the DBC's cycle time, else "
                        "1 ms)")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from canrls.c_export import export_c, load_source

    cfg, model, energy, source = load_source(args.model)
    print(export_c(cfg, args.out, model=model, dt=args.dt, energy=energy, source=source,
                   what=f"--out {args.out}"))
    return 0
