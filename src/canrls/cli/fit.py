"""``canrls fit LOG [LOG ...]``: replay recorded CAN logs and print every identified parameter.

Several logs identify one model from all of them (:class:`canrls.replay.LogFiles`: the
decoder, pairer and filter restart at every file, no segment is bridged; the calibration
window is the start of the first log). ``--save-model FILE`` writes the identified model
as JSON (:mod:`canrls.modelfile`, ``docs/model_file.md``) for ``canrls validate``.

Reads candump ``.log`` (and ``.asc``, ``.blf``, ``.trc``, ``.csv`` through python-can),
decodes the feedback frames strictly with the DBC, pairs them into samples, and runs the
same pipeline as the daemon: float and fixed-point RLS side by side. Prints every
parameter (float, ±σ, fixed, unit), the residual RMS and fit %. ``--fixed target`` takes
the fixed column from the target's integer path instead (:mod:`canrls.target.fit`): the
frames decoded, filtered and estimated in integers as ``canrls export-c``'s C does, bit
for bit (``extra``: ``"fixed"`` in ``--json``).

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
      "period": {"value": 0.001, "source": "measured",   # or "--period 0.001", the DBC
                 "measured": 0.001, "jitter": 1e-07, "intervals": 510},
      "start": {"t0": 1700000000.123, "date": "2023-11-14 22:13:20.123000 UTC",
                "relative": true},                      # times are from the log's start
      "axis": {"axis": "rotary", "dbc_axis": "rotary", "units": {"current": "mA", ...}},
      "calibration": {..., "defaults": {"coulomb_band": 0.04, "stribeck_speed": 1.0}},
      "source": "drive.log"
    }

With no configuration file, ``--dbc`` and ``--signal`` are all a user's drive needs: the
period comes from the timestamps, the axis from the DBC units, and the defaults that
depend on a unit from the data (docs/architecture.md, "Control period" and "Defaults
from the data"). A log without the mapped messages, too few usable samples or an
impossible value is an error (exit 1) that says what it found.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from canrls.cli._common import (
    Progress,
    add_log_arguments,
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
    add_log_arguments(p, "several logs identify one model (segments never bridged "
                         "across files)")
    add_model_options(p)
    p.add_argument("--save-model", metavar="FILE",
                   help="write the identified model (effects, parameters with sigma and "
                        "unit, configuration, calibration) as JSON for 'canrls validate'")
    p.add_argument("--fixed", choices=("kernel", "target"), default="kernel",
                   help="the fixed-point column: the kernel fed by the float front end, as "
                        "the daemon runs it (default), or the target's whole integer path "
                        "from the frames on, as the C of 'canrls export-c' runs it (bit for "
                        "bit; docs/target.md)")
    add_progress_option(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from canrls.replay import fit_logs, prepare

    cfg = setup(args)
    protocol, model, settings = prepare(cfg)
    res = fit_logs(args.log, protocol, model, settings,
                   progress=Progress("replay", quiet=args.quiet).callback,
                   skip_bad_lines=args.skip_bad_lines)
    if args.fixed == "target":
        from canrls.target.fit import target_fixed

        res = target_fixed(res, args.log, protocol, settings)
    saved = None
    if args.save_model:
        from canrls.modelfile import SavedModel

        saved = SavedModel.from_fit(res, cfg, list(args.log)).save(args.save_model)
    if args.json:
        d = res.to_dict()
        if saved is not None:
            d["saved_model"] = str(saved)
        print_json(d)
    else:
        sys.stdout.write(res.format() + "\n")
        fx = res.extra.get("fixed")
        if fx:
            sys.stdout.write(
                f"fixed point: the target's integer path from the frames on ({fx['samples']} "
                f"samples; updates {fx['updates']}, rescales {fx['rescales']}"
                + (f", frames rejected or dropped {fx['rejected']}" if fx["rejected"] else "")
                + ")\n")
        if saved is not None:
            sys.stdout.write(f"model saved: {saved}\n")
    return 0
