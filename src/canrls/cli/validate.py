"""``canrls validate LOG [LOG ...] --model FILE``: a saved model against other recordings.

Predicts the logs with the parameters of a model saved by ``canrls fit --save-model``
without re-estimating anything (:mod:`canrls.diagnosis.validation`) and reports fit %,
residual RMS (overall and per log) and where the model fails. The DBC and mapping
default to the file's; options that would change the model are refused. ``--report``
and ``--json``: docs/model_file.md, "``canrls validate``".
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
    add_report_option,
    overrides,
    print_json,
)

__all__ = ["add_subparser", "run"]


def add_subparser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "validate", help="predict other logs with a saved model (no re-estimation)",
        description="Predict CAN logs with the parameters of a model saved by 'canrls fit "
                    "--save-model', without re-estimating, and report fit %, residual RMS "
                    "and where the model fails.")
    add_log_arguments(p, "several logs are predicted as one record (segments never "
                         "bridged across files)")
    p.add_argument("--model", "-m", required=True, metavar="FILE",
                   help="model file written by 'canrls fit --save-model'")
    add_report_option(p)
    add_model_options(p)
    add_progress_option(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from canrls.diagnosis.validation import validate_logs
    from canrls.processor.axes import AXIS_KINDS
    from canrls.processor.config import AppConfig
    from canrls.processor.modelfile import SavedModel

    if args.report:
        # fail before the long part when the figures cannot be drawn
        from canrls.core.webpage import require_matplotlib
        from canrls.diagnosis.figures import MATPLOTLIB

        require_matplotlib(*MATPLOTLIB)
    from canrls.core.errors import ConfigError

    saved = SavedModel.load(args.model)
    kind = args.axis if args.axis in AXIS_KINDS else None  # else the name of an axis
    # the model is the file's: options that would change it are refused, not ignored
    # (the same value as saved is accepted: scripts pass one set of options to all)
    settings = saved.config().settings()
    effects = None if args.effects is None else \
        [e.strip() for e in args.effects.split(",") if e.strip()]
    differ = [f"{flag} {typed} (saved: {have})" for flag, typed, want, have in (
        ("--effects", args.effects, effects, ",".join(saved.effects)),
        ("--kt", args.kt, args.kt, saved.model.get("kt")),
        ("--axis", kind, kind, saved.model.get("axis")),
        ("--lambda", args.lam, args.lam, settings.lam),
        ("--alpha", args.alpha, args.alpha, settings.alpha))
        if typed is not None and want != (saved.effects if flag == "--effects" else have)]
    if differ:
        raise ConfigError(f"validate: {'; '.join(differ)}: the model, its parameters and "
                          f"settings are the saved file's ({args.model}); to change them, "
                          f"fit again with 'canrls fit ... --save-model'")
    base = saved.config()
    cfg = AppConfig.load(args.config) if args.config else AppConfig(source=base.source)
    # the protocol: the saved one, unless the command line or --config gives another
    if not args.config:
        cfg.can = dict(base.can)
        cfg.signals = dict(base.signals)
        if not args.signal:
            cfg.signal_overrides = list(base.signal_overrides)
    cfg = cfg.apply(overrides(args)).one_axis()
    rep = validate_logs(args.log, saved, cfg.protocol(), model_file=args.model,
                        progress=Progress("validate", quiet=args.quiet).callback,
                        skip_bad_lines=args.skip_bad_lines)
    page = rep.write_html(args.report) if args.report else None
    if args.json:
        d = rep.to_dict()
        if page is not None:
            d["report"] = str(page)
        print_json(d)
    else:
        sys.stdout.write(rep.format() + "\n")
        if page is not None:
            sys.stdout.write(f"\nreport: {page}\n")
    return 0
