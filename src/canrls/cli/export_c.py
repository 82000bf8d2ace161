"""``canrls export-c``: the C code of a model for the target.

Writes into ``--out`` the whole estimator (``canrls_target.h/.c``, the model's constants
``canrls_model.h/.c``: the drive's frames in, canrls' parameter frames out, in integers;
:mod:`canrls.firmware.target_export`), the fixed-point RLS kernel (``canrls_fixed.h/.c``), the
configuration of the model's equations (``canrls_config.h/.c``: parameters, scaling, Q
formats, the kernel's plan and prior), cantools' C codecs of canrls' parameter and
command frames (``canrls_frames.h/.c``), a README and a Makefile; with ``--vectors``
test vectors from logs and the host test that replays them (:mod:`canrls.firmware.kernel_export`).
``--model`` is a TOML configuration or a saved model (``canrls fit --save-model``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from canrls.firmware.load import Source

__all__ = ["add_subparser", "run"]


def add_subparser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "export-c", help="write the whole estimator in C for the target, with test vectors",
        description="Write a directory that compiles for the target: the whole estimator "
                    "(the drive's frames in, canrls' parameter frames out, in integers), the "
                    "fixed-point RLS kernel, the configuration header of the model, a README "
                    "and a Makefile; with --vectors, test vectors from logs and a host test "
                    "that checks the C bit for bit against the specification.")
    p.add_argument("--model", required=True, metavar="FILE",
                   help="TOML configuration, or a saved model (.json, canrls fit "
                        "--save-model)")
    p.add_argument("--axis", metavar="NAME",
                   help="the axis to export of a configuration with several ([[axes]], "
                        "docs/configuration.md)")
    p.add_argument("--out", type=Path, default=Path("canrls_c"), metavar="DIR",
                   help="output directory, made if missing (default: canrls_c); each file "
                        "is written to a temporary beside it and renamed")
    p.add_argument("--dt", type=float, default=None, metavar="S",
                   help="control period in seconds (default: the saved model's, else the "
                        "DBC's cycle time, else 1 ms)")
    p.add_argument("--frames", choices=("canrls", "none"), default="canrls",
                   help="the estimator frames: canrls' own DBC's (default), or none (the "
                        "firmware sends the estimate itself)")
    p.add_argument("--vectors", nargs="+", default=(), metavar="LOG",
                   help="logs of the drive's frames (in the model's DBC): write them and the "
                        "integers the specification computes as test vectors, with the host "
                        "test that replays them (make -C DIR test)")
    p.add_argument("--every", type=int, default=1000, metavar="N",
                   help="samples between the state records of the vectors (default 1000)")
    p.add_argument("--feedforward", type=int, default=None, metavar="N",
                   help="also the anticogging map of a saved model as a C function in fixed "
                        "point, N points per revolution (canrls_feedforward.h/.c; "
                        "docs/tune.md)")
    p.add_argument("--feedforward-form", choices=("table", "harmonics"), default="table",
                   help="the map as a table of N points (default) or as its harmonics "
                        "(N is then checked but not used)")
    p.add_argument("--kernel-only", action="store_true",
                   help="only the kernel, the configuration and the frame codecs (what a "
                        "model the whole estimator cannot run, with user terms, gets anyway, "
                        "with the reason on stderr)")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from canrls.core.errors import ConfigError
    from canrls.firmware.kernel_export import export_c
    from canrls.firmware.load import load

    if args.every < 1:
        raise ConfigError(f"--every {args.every}: must be at least 1")
    if args.kernel_only and args.vectors:
        raise ConfigError("--vectors: the test vectors need the whole estimator "
                          "(not --kernel-only)")
    # the model, its calibration and its control period: one loader, one decision
    src = load(args.model, args.dt, args.axis)
    ff_texts = (_feedforward(src, args.model, args.feedforward, args.feedforward_form)
                if args.feedforward is not None else None)
    tm = texts = None
    if not args.kernel_only:
        from canrls.firmware.load import target_model
        from canrls.firmware.target_export import target_texts
        from canrls.firmware.target_model import TargetError

        # generated (or refused: a model the target cannot run, a log that cannot be
        # read) before anything is written
        try:
            tm = target_model(src, frames=args.frames != "none")
        except TargetError as e:
            if args.vectors:
                raise
            # the kernel and its configuration still serve a firmware that builds its
            # own regressors: written, and the reason the rest is not said
            print(f"canrls export-c: the whole estimator is not written: {e}",
                  file=sys.stderr)
        if tm is not None:
            texts = target_texts(src, tm, vectors=args.vectors, every=args.every)
    print(export_c(src.config, args.out, model=src.model, dt=src.dt, energy=src.energy,
                   source=src.label, what=f"--out {args.out}", frames=args.frames != "none"))
    if tm is not None:
        from canrls.firmware.target_export import export_target

        print(export_target(src, args.out, tm, what=f"--out {args.out}", texts=texts))
    if ff_texts is not None:
        from canrls.core.files import write_texts

        texts_ff, line = ff_texts
        write_texts(args.out, texts_ff, f"--out {args.out}")
        print(line)
    return 0


def _feedforward(src: Source, path: str, points: int, form: str
                 ) -> tuple[list[tuple[str, str]], str]:
    """The anticogging map's C of the saved model ``src`` read from ``path`` (before
    anything is written) and the line that says it."""
    from canrls.control.feedforward import check_points, feedforward
    from canrls.control.fixed_map import (
        feedforward_c,
        fixed_friction,
        fixed_harmonics,
        fixed_map,
        friction_c,
        harmonics_c,
        map_c,
    )
    from canrls.core.errors import ConfigError

    check_points(points, "--feedforward")
    if src.saved is None:
        raise ConfigError(f"--feedforward: needs a saved model (.json), not {path}")
    ff = feedforward(src.saved.build_model(), src.saved.parameters, source=path)
    if not ff.has_map:
        raise ConfigError(f"--feedforward: no anticogging map: {ff.no_map_reason()}")
    if form == "harmonics":
        fh = fixed_harmonics([(h.order, h.cos if h.order == 0 else h.amplitude, h.phase)
                              for h in ff.harmonics()], ff.unit)
        parts = [harmonics_c(fh)]
        what = (f"the anticogging map as {len(fh.orders)} harmonics in Q{fh.frac} "
                f"{ff.unit} (orders {', '.join(map(str, fh.orders)) or 'none'})")
    else:
        fm = fixed_map(ff.position_map(points)[1], ff.unit)
        parts = [map_c(fm)]
        what = (f"the anticogging map, {points} points in Q{fm.frac} {ff.unit}, table "
                f"{fm.flash} bytes of flash")
    sp = ff.to_dict()["speed"]
    par = sp["parameters"]
    if any(k in par for k in ("viscous.B", "coulomb.Tc", "stribeck.Ts")):
        fr = fixed_friction(par.get("viscous.B", 0.0), par.get("coulomb.Tc", 0.0),
                            par.get("stribeck.Ts", 0.0), sp["coulomb_band"],
                            sp["stribeck_speed"], ff.unit)
        parts.append(friction_c(fr))
        what += f"; the friction at the speed reference in Q{fr.frac}"
    head, c_src = feedforward_c(parts, path)
    return ([("canrls_feedforward.h", head), ("canrls_feedforward.c", c_src)],
            f"canrls_feedforward.c: {what}")
