"""``canrls tune``: compensation and speed-loop gains from a saved model or from logs.

    canrls tune --model drive.json --bandwidth 20 --points 1024 --out tuned/
    canrls tune drive.log --kt 0.1 -e inertia,viscous,coulomb,cogging:6 --out tuned/

The first line printed is the answer (what is compensated, the ripple before and after,
the gains); ``--out DIR`` writes ``feedforward.json``, ``anticogging.csv`` and
``gains.json`` (:mod:`canrls.control.tuner`; docs/tune.md).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from canrls.cli._common import add_model_options, fit_model, number, print_json, setup

__all__ = ["add_subparser", "run"]


def add_subparser(subparsers: Any) -> argparse.ArgumentParser:
    from canrls.control.tune_limits import (
        DEFAULT_DELAY,
        DEFAULT_MARGIN,
        DEFAULT_POINTS,
        DEFAULT_SHARE,
        MAX_POINTS,
    )

    p = subparsers.add_parser(
        "tune", help="feedforward (anticogging map, friction) and speed-loop gains from a "
                     "model",
        description="Turn an identified model into control: the feedforward torque of the "
                    "effects the data support (anticogging map, harmonics, friction), the "
                    "ripple before and after, and speed-loop PI gains for a bandwidth or "
                    "the symmetric optimum.")
    p.add_argument("log", metavar="LOG", nargs="*",
                   help="CAN log(s) to identify the model on (as 'canrls fit'); or --model")
    p.add_argument("--model", "-m", metavar="FILE",
                   help="a saved model (canrls fit --save-model)")
    p.add_argument("--points", "-n", type=int, default=DEFAULT_POINTS, metavar="N",
                   help=f"points of the anticogging map per revolution (pitch), 2 to "
                        f"{MAX_POINTS} (default {DEFAULT_POINTS})")
    p.add_argument("--share", type=number, default=DEFAULT_SHARE, metavar="S",
                   help=f"leave out a term whose sigma is above this share of its size "
                        f"(default {DEFAULT_SHARE:g})")
    p.add_argument("--bandwidth", type=number, metavar="HZ",
                   help="closed speed loop's bandwidth to tune for [Hz] (default: the "
                        "symmetric optimum)")
    p.add_argument("--symmetric-optimum", action="store_true",
                   help="tune for the symmetric optimum (the default without --bandwidth "
                        "where the current loop's time constant is known)")
    p.add_argument("--phase-margin", type=number, default=DEFAULT_MARGIN, metavar="DEG",
                   help=f"phase margin with --bandwidth (default {DEFAULT_MARGIN:g})")
    p.add_argument("--delay", type=number, default=DEFAULT_DELAY, metavar="PERIODS",
                   help=f"the loop's delay in control periods (default {DEFAULT_DELAY:g}: "
                        f"one of computation, half of the hold)")
    p.add_argument("--current-tau", type=number, metavar="SECONDS",
                   help="time constant of the current loop (default: L/R of the "
                        "electrical equation; with --bandwidth and none: ideal)")
    p.add_argument("--rated-speed", type=number, metavar="RAD_S",
                   help="rated speed [rad/s; m/s] for the per-unit gains")
    p.add_argument("--out", "-o", metavar="DIR",
                   help="write feedforward.json, anticogging.csv and gains.json into DIR")
    add_model_options(p)
    p.set_defaults(func=run, tune_parser=p)
    return p


#: the options of the fit that a saved model already holds
_FIT_ONLY = ("config", "dbc", "signal", "rated_current", "increments_per_rev", "effects", "kt",
             "axis", "lam", "alpha")


def _saved(args: argparse.Namespace) -> Any:
    """The saved model: read from --model, or identified on the logs."""
    from canrls.processor.modelfile import SavedModel

    if bool(args.log) == bool(args.model):
        args.tune_parser.error("give either LOG ... or --model FILE")
    if args.model:
        given = [f"--{k.replace('_', '-')}" for k in _FIT_ONLY
                 if getattr(args, k, None) is not None]
        if given:
            from canrls.core.errors import ConfigError

            raise ConfigError(f"tune: {', '.join(given)}: the model is the saved file's "
                              f"({args.model}); to change it, fit again (or tune on the "
                              f"logs)")
        return SavedModel.load(args.model), str(args.model)
    from canrls.processor.config import prepare
    from canrls.processor.replay import fit_logs

    cfg = setup(args)
    protocol, model, settings = prepare(cfg)
    model, _ = fit_model(args.log, protocol, model, settings)
    res = fit_logs(args.log, protocol, model, settings)
    return SavedModel.from_fit(res, cfg, list(args.log)), "the fit of " + ", ".join(args.log)


def run(args: argparse.Namespace) -> int:
    from canrls.control.tuner import TuneRequest, tune
    from canrls.core.files import check_path, output_dir

    if args.out is not None:
        check_path(args.out, f"--out {args.out}")
    saved, source = _saved(args)
    req = TuneRequest(points=args.points, share=float(args.share),
                      bandwidth=None if args.bandwidth is None else float(args.bandwidth),
                      symmetric_optimum=args.symmetric_optimum,
                      margin=float(args.phase_margin), delay=float(args.delay),
                      current_tau=None if args.current_tau is None else float(args.current_tau),
                      period=None if args.period is None else float(args.period),
                      rated_speed=None if args.rated_speed is None else float(args.rated_speed),
                      rated_torque=None if args.rated_torque is None
                      else float(args.rated_torque))
    res = tune(saved, req, source=source)
    written = res.write(output_dir(args.out, f"--out {args.out}")) if args.out else []
    earlier = res.earlier(args.out, written) if args.out else []
    if args.json:
        d = res.to_dict()
        d["written"] = [str(p) for p in written]
        d["earlier"] = [str(p) for p in earlier]
        print_json(d)
    else:
        sys.stdout.write(res.format() + "\n")
        for p in written:
            sys.stdout.write(f"wrote {p}\n")
        for p in earlier:
            sys.stdout.write(f"kept {p}: an earlier tune's, not of this one\n")
    return 0
