"""``canrls fit LOG [LOG ...]``: replay recorded CAN logs and print every identified parameter.

Several logs identify one model from all of them (no segment is bridged; the
calibration window is the start of the first log); ``--save-model FILE`` writes the
model as JSON for ``canrls validate`` (docs/model_file.md); ``--json`` prints one object
(README.md, "Command line"). The fixed column is the target's integer path
(:mod:`canrls.firmware.target_fit`, docs/target.md): the frames decoded, filtered and estimated
in integers by the C ``canrls export-c`` writes, as the daemon runs it, bit for bit;
``--fixed kernel`` takes the fixed-point kernel fed by the float front end instead.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from typing import TYPE_CHECKING, Any

from canrls.cli._common import (
    Progress,
    add_log_arguments,
    add_model_options,
    add_progress_option,
    fit_model,
    print_json,
    setup,
)

if TYPE_CHECKING:
    from canrls.diagnosis.results import SearchResult

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
    p.add_argument("--fixed", choices=("kernel", "target"), default=None,
                   help="the fixed-point column: 'target' (default) the target's whole "
                        "integer path from the frames on, as the C of 'canrls export-c' and "
                        "the daemon run it (bit for bit; by default a model the target "
                        "cannot run takes the kernel's column, and the output says why); "
                        "'kernel' the fixed-point kernel fed by the float front end "
                        "(docs/target.md)")
    add_progress_option(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from canrls.processor.config import prepare
    from canrls.processor.replay import fit_logs

    cfg = setup(args, every_axis=True)
    if len(cfg.axes) > 1 and cfg.axis_name is None:
        return _fit_machine(args, cfg)
    cfg = cfg.one_axis()
    protocol, model, settings = prepare(cfg)
    model, searched = fit_model(args.log, protocol, model, settings,
                                skip_bad_lines=args.skip_bad_lines)
    res = fit_logs(args.log, protocol, model, settings,
                   progress=Progress("replay", quiet=args.quiet).callback,
                   skip_bad_lines=args.skip_bad_lines)
    res = _fixed_column(res, args, protocol, settings)
    saved = None
    if args.save_model:
        from canrls.processor.modelfile import SavedModel

        saved = SavedModel.from_fit(res, cfg, list(args.log)).save(args.save_model)
    found = _found(searched)
    if args.json:
        d = res.to_dict()
        d["search"] = [r.to_dict() for r in searched]
        if saved is not None:
            d["saved_model"] = str(saved)
        print_json(d)
    else:
        sys.stdout.write(res.format() + "\n")
        sys.stdout.write("".join(line + "\n" for line in found))
        if res.fixed is not None:
            sys.stdout.write(res.fixed.format() + "\n")
        if saved is not None:
            sys.stdout.write(f"model saved: {saved}\n")
    return 0


def _found(searched: tuple[SearchResult, ...]) -> list[str]:
    """A line for each value searched, with how to set it for the daemon."""
    return [f"{r.text()}: searched on the record; set [model.stribeck] speed = "
            f"{r.value:.4g} for 'canrls run', which cannot search" for r in searched]


def _fixed_column(res: Any, args: argparse.Namespace, protocol: Any, settings: Any) -> Any:
    """``res`` with its fixed column from the target's integer path (the default, or
    ``--fixed target``: then a model the target cannot run is an error), or as the
    pipeline's kernel gave it (``--fixed kernel``)."""
    if args.fixed == "kernel":
        return res
    from canrls.firmware.target_fit import target_fixed
    from canrls.firmware.target_model import TargetError
    from canrls.processor import KernelFallback

    try:
        return target_fixed(res, args.log, protocol, settings,
                            skip_bad_lines=args.skip_bad_lines)
    except TargetError as e:
        if args.fixed == "target":
            raise
        return dataclasses.replace(res, fixed=KernelFallback(str(e)))


def _fit_machine(args: argparse.Namespace, cfg: Any) -> int:
    """``canrls fit LOG --axes ...`` without ``--axis``: every axis in one pass."""
    from canrls.core.errors import ConfigError, EstimatorError
    from canrls.processor.config import prepare
    from canrls.processor.replay import fit_axes

    if args.save_model:
        raise ConfigError("--save-model: one axis at a time with several (--axis NAME)")
    axes = {name: prepare(c) for name, c in cfg.axis_configs().items()}
    # each axis's Stribeck speed searched on its own frames, as canrls fit --axis NAME does
    searched: dict[str, tuple[SearchResult, ...]] = {}
    for name, (protocol, model, settings) in axes.items():
        model, searched[name] = fit_model(args.log, protocol, model, settings,
                                          skip_bad_lines=args.skip_bad_lines)
        axes[name] = axes[name]._replace(model=model)
    res = fit_axes(args.log, axes, progress=Progress("replay", quiet=args.quiet).callback,
                   skip_bad_lines=args.skip_bad_lines)
    # each axis's fixed column from its own target path (the frames of the others are
    # not its messages: the target passes them by)
    res = dataclasses.replace(res, fits={
        name: fit if name in res.errors else _fixed_column(fit, args, axes[name][0], axes[name][2])
        for name, fit in res.fits.items()})
    if args.json:
        d = res.to_dict()
        for name, found in searched.items():
            if name not in res.errors:
                d["axes"][name]["search"] = [r.to_dict() for r in found]
        print_json(d)
    else:
        sys.stdout.write(res.format() + "\n")
        sys.stdout.write("".join(f"axis {name}: {line}\n" for name, found in searched.items()
                                 for line in _found(found)))
    if res.errors:
        name, why = next(iter(res.errors.items()))
        raise EstimatorError(f"axis {name}: {why}"
                             + (f" (and {len(res.errors) - 1} more axes)"
                                if len(res.errors) > 1 else ""))
    return 0
