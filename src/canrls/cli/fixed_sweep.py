"""``canrls fixed-sweep``: fixed-point parameter error against word length and Q formats.

Replays logs (several identify one model, as ``canrls fit`` reads them) or simulates a
scenario through the pipeline, keeps the normalised
regressors of every used sample, computes the float reference on them and runs the
fixed-point kernel for every combination of state word (``--word``), accumulator
(``--acc``) and input word (``--input``), Q formats chosen automatically for each.
Prints the largest relative parameter error of each configuration against float (each
parameter against ``max(|float|, 3 sigma)``, as ``canrls fit`` measures its divergence), its
saturations, and recommends the smallest configuration within ``--tol`` (0.1 %).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from canrls.cli._common import (
    Progress,
    add_model_options,
    add_progress_option,
    fit_model,
    print_json,
    setup,
)
from canrls.core.errors import ConfigError

__all__ = ["add_subparser", "run"]


def _bits(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list of bits") \
            from None


def add_subparser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "fixed-sweep", help="fixed-point error against word length and Q formats",
        description="Run the fixed-point RLS for several word lengths on logs (or a "
                    "simulated scenario), print each configuration's largest relative "
                    "parameter error against the float reference, and recommend one.")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("log", nargs="*", default=[], metavar="LOG",
                     help="CAN log(s) to replay; several identify one model, as in "
                          "'canrls fit'")
    src.add_argument("--scenario", metavar="NAME",
                     help="simulate this scenario instead (standard, linear, poor)")
    p.add_argument("--duration", type=float, default=30.0,
                   help="simulated seconds with --scenario (default 30)")
    p.add_argument("--seed", type=int, default=0, help="seed with --scenario (default 0)")
    p.add_argument("--word", type=_bits, default=[16, 24, 32], metavar="BITS,...",
                   help="state word lengths (default 16,24,32)")
    p.add_argument("--acc", type=_bits, default=[32, 48, 64], metavar="BITS,...",
                   help="accumulator lengths (default 32,48,64)")
    p.add_argument("--input", type=_bits, default=[16, 32], metavar="BITS,...",
                   help="input word lengths of phi and y (default 16,32)")
    p.add_argument("--tol", type=float, default=1e-3,
                   help="tolerance on every parameter's error, relative to max(|float|, "
                        "3 sigma) as in 'canrls fit' (default 1e-3)")
    p.add_argument("--max-samples", type=int, default=200_000,
                   help="use at most this many samples (default 200000)")
    add_model_options(p)
    add_progress_option(p)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from canrls.estimation.estimates import used_rows
    from canrls.estimation.fixed.sweep import sweep
    from canrls.estimation.rls import RLS
    from canrls.processor import FrameProcessor
    from canrls.processor.config import prepare

    cfg = setup(args)
    protocol, model, settings = prepare(cfg)
    if not args.scenario:
        model, _ = fit_model(args.log, protocol, model, settings)
    proc = FrameProcessor(protocol, model, settings)
    blocks = []
    if args.scenario:
        from canrls.sim.scenario import scenario, simulate

        effects = cfg.model.get("effects")
        res = simulate(scenario(args.scenario, effects=",".join(effects) if effects else None,
                                seed=args.seed, duration=args.duration))
        blocks.append(proc.process_samples(res.measured, record=True))
        source = f"scenario {args.scenario} ({args.duration:g} s, seed {args.seed})"
    else:
        from canrls.processor.replay import LogFiles

        files = LogFiles(args.log, proc,
                         progress=Progress("replay", quiet=args.quiet).callback)
        for s in files.samples():
            blocks.append(proc.process_samples(s, record=True))
            if sum(b.samples for b in blocks) >= args.max_samples:
                break
        source = ", ".join(args.log)
    blocks.append(proc.flush(record=True))
    pipe = proc.pipeline
    settings = pipe.settings
    out: dict[str, Any] = {"source": source, "equations": {}}
    text = [f"{source}"]
    for k, est in enumerate(pipe.estimators):
        eq = est.equation
        phi, y = used_rows([b.equations[k] for b in blocks], eq.scaling.output)
        phi, y = phi[: args.max_samples], y[: args.max_samples]
        if len(y) == 0:
            raise ConfigError(f"{source}: no samples to sweep")
        ref = RLS(eq.n, lam=settings.lam, alpha=est.ridge, trace_max=settings.trace_max)
        ref.run(phi, y, record=False)
        res_sw = sweep(phi, y, ref.theta, lam=settings.lam, alpha=est.ridge,
                       trace_max=settings.trace_max, word_bits=args.word, acc_bits=args.acc,
                       input_bits=args.input, theta_max=settings.theta_max, tol=args.tol,
                       sigma=ref.std())
        d = res_sw.to_dict()
        d["parameters"] = [p.name for p in eq.parameters]
        d["samples"] = len(y)
        out["equations"][eq.name] = d
        text.append(f"\n{eq.name} equation: {len(y)} samples, parameters "
                    f"{', '.join(p.name for p in eq.parameters)}")
        text.append(str(res_sw))
        if res_sw.recommended is not None and res_sw.recommended.config is not None:
            c = res_sw.recommended.config
            text.append("  Q formats: " + ", ".join(f"{n}={q}" for n, q in c.formats().items()))
    if args.json:
        print_json(out)
    else:
        sys.stdout.write("\n".join(text) + "\n")
    return 0
