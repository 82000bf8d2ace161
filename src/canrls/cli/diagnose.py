"""``canrls diagnose LOG [LOG ...]``: where the model fails, which effect is missing.

Takes every option of ``canrls fit`` but ``--fixed`` (the same replay: same samples, same
parameters; the fixed-point column is the kernel's, fed by the float front end), plus
``--add NAME`` (refit with it), ``--report DIR`` (an HTML page with figures) and
``--max-order K``; several logs are diagnosed as one record. Text by default;
``--json`` prints one object (docs/diagnose.md documents every key).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from canrls.cli._common import (
    Progress,
    add_log_arguments,
    add_max_order_option,
    add_model_options,
    add_progress_option,
    add_report_option,
    fit_model,
    print_json,
    setup,
)

__all__ = ["add_subparser", "run"]


def add_subparser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "diagnose", help="compare the model with a log: where it fails, which effect is missing",
        description="Replay a CAN log as 'canrls fit' does, compare the model with the "
                    "measurements (fit, residual RMS, whiteness), show where it fails (speed, "
                    "position, current, acceleration, time, rotation order), rank the "
                    "effects of the library the model lacks, and with --add refit and print "
                    "before and after side by side. The decoded samples are kept in an "
                    "anonymous temporary file in TMPDIR (up to 40 bytes a sample, gone on exit), "
                    "or in memory if none can be made.")
    add_log_arguments(p, "several logs are diagnosed as one record (segments never "
                         "bridged across files)")
    add_model_options(p)
    add_progress_option(p)
    g = p.add_argument_group("diagnosis")
    g.add_argument("--add", action="append", default=[], metavar="NAME",
                   help="add an effect and refit (repeatable), e.g. --add coulomb "
                        "--add cogging:24; 'cogging' alone takes the order the search found")
    add_report_option(g)
    g.add_argument("--save-model", metavar="FILE",
                   help="write the model (after --add, if any) with its parameters as JSON "
                        "for 'canrls validate' (as 'canrls fit --save-model')")
    add_max_order_option(g, "searched")
    p.set_defaults(func=run)
    return p


def _compensation(analysis: Any, found: Any) -> tuple[str, dict[str, Any]] | None:
    """What compensating the model's position terms would leave of their ripple; for
    position effects found but not added (``found``: their candidates), their ripple."""
    from canrls.control.tuner import compensation, found_ripple

    if found:
        line = found_ripple(analysis.model, {c.effect: {k: v for k, (v, _) in
                                                        c.parameters.items()}
                                             for c in found})
        if line is not None:
            return line
    return compensation(analysis.model, {p.name: p.to_dict()
                                         for p in analysis.estimates.parameters})


def run(args: argparse.Namespace) -> int:
    from canrls.core.errors import EstimatorError
    from canrls.diagnosis.analysis import diagnose_log
    from canrls.processor.config import prepare
    from canrls.processor.replay import too_few_samples

    if args.report:
        # fail before the long part when the figures cannot be drawn
        from canrls.core.webpage import require_matplotlib
        from canrls.diagnosis.figures import MATPLOTLIB

        require_matplotlib(*MATPLOTLIB)
    cfg = setup(args)
    protocol, model, settings = prepare(cfg)
    model, _ = fit_model(args.log, protocol, model, settings,
                         skip_bad_lines=args.skip_bad_lines)
    rep = diagnose_log(args.log, protocol, model, settings, add=args.add,
                       progress=Progress("diagnose", quiet=args.quiet).callback,
                       max_order=args.max_order, skip_bad_lines=args.skip_bad_lines)
    few = rep.frames and too_few_samples(rep.before.model, rep.before.estimates, rep.frames,
                                         rep.period.value if rep.period is not None
                                         else None, settings)
    if few:
        raise EstimatorError(f"{', '.join(args.log)}: {few}")
    final = rep.after if rep.after is not None else rep.before
    rep.compensation = _compensation(final, () if rep.after is not None else
                                     [c for c in rep.candidates if c.suggested])
    page = rep.write_html(args.report) if args.report else None
    saved = None
    if args.save_model:
        from canrls.processor.modelfile import SavedModel

        saved = SavedModel.from_parts(final.model, final.estimates, None, cfg,
                                      list(args.log)).save(args.save_model)
    if args.json:
        d = rep.to_dict()
        if page is not None:
            d["report"] = str(page)
        if saved is not None:
            d["saved_model"] = str(saved)
        print_json(d)
    else:
        head = []
        if rep.start is not None and rep.start.date:
            head.append(f"log starts {rep.start.date}; times below are from that start")
        if rep.period is not None and rep.period.value:
            head.append(f"control period {rep.period.value * 1e3:.6g} ms ({rep.period.source})")
        m = getattr(rep, "model", None)
        if m is not None:
            u = "m/s" if m.axis == "linear" else "rad/s"
            ms = settings.min_speed if settings.min_speed is not None else 5 * m.coulomb_band
            head.append(f"axis {m.axis}; values used: Coulomb band {m.coulomb_band:.4g} {u} "
                        f"(minimum speed {ms:.4g} {u} with sign-dependent friction)"
                        # a candidate's Stribeck speed is searched: the model's only if used
                        + (f", Stribeck speed {m.stribeck_speed:.4g} {u}"
                           if "stribeck" in m.effect_names else "")
                        + (f", pitch {m.pitch:.4g} m" if m.axis == "linear" else ""))
        sys.stdout.write(rep.format(head) + "\n")
        if page is not None:
            sys.stdout.write(f"\nreport: {page}\n")
        if saved is not None:
            sys.stdout.write(f"model saved: {saved}\n")
    return 0
