"""``canrls fit LOG``: replay a recorded CAN log and print every identified parameter.

Reads candump ``.log`` (and ``.asc``, ``.blf``, ``.trc``, ``.csv`` through python-can),
decodes the feedback frames strictly with the DBC, pairs them into samples, and runs the
same pipeline as the daemon: float and fixed-point RLS side by side. Prints every
parameter (float, ±σ, fixed, unit), the residual RMS and fit %.

``--json`` prints one object::

    {
      "parameters": {"coulomb.Tc": {"value": 0.0199, "sigma": 1.6e-05, "unit": "N·m",
                                    "fixed": 0.0199, "effect": "coulomb",
                                    "equation": "mechanical", "description": "..."}, ...},
      "residual_rms": 0.0005,        # target unit (N·m with --kt, else A)
      "fit_percent": 97.1,           # 100 (1 - |y - yhat| / |y - mean y|), MATLAB compare
      "samples": 59950, "effects": [...], "unit": "N·m",
      "equations": {"mechanical": {...}, "electrical": {...}},
      "frames": {"total": ..., "rejected": {reason: n}, "lost": {...}, "foreign": n,
                 "pairing": {...}},
      "source": "drive.log"
    }
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from canrls.cli._common import (
    Progress,
    add_model_options,
    add_progress_option,
    print_json,
    setup,
)

__all__ = ["add_subparser", "run"]


def add_subparser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "fit", help="replay a CAN log and identify the parameters",
        description="Replay a CAN log through the estimation pipeline (float and fixed-point "
                    "RLS) and print every parameter with unit and sigma, the residual RMS and "
                    "the fit.")
    p.add_argument("log", metavar="LOG", help="CAN log: .log (candump), .asc, .blf, .trc, .csv")
    add_model_options(p)
    add_progress_option(p)
    p.add_argument("--skip-bad-lines", action="store_true",
                   help="count unparsable log lines instead of stopping at the first")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from canrls.replay import fit_log, prepare

    cfg = setup(args)
    protocol, model, settings = prepare(cfg)
    res = fit_log(args.log, protocol, model, settings,
                  progress=Progress("replay", quiet=args.quiet).callback,
                  skip_bad_lines=args.skip_bad_lines)
    if args.json:
        print_json(res.to_dict())
    else:
        sys.stdout.write(res.format() + "\n")
    return 0
