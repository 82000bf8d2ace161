#!/usr/bin/env python3
"""What one lost sample costs the estimate: the straight-line gap fill against the rest.

A measurement, not a test (docs/reliability.md, *Why not "within 2 sigma of the
twin"*). The simulated drive (``canrls.sim``) runs through the float pipeline of
``canrls fit`` (``canrls.processor.replay.fit_frames``) once without faults (the twin), then
with the same ``--fraction`` of its control periods taken away (both frames of each,
at seeded random places, far apart on average: single-sample gaps) in four ways:

``line``    the frames are dropped: the pipeline fills each gap on a straight line
            (``canrls.estimation.selection.GapFiller``), the filled row runs through
            the state-variable filter and never updates the estimators (as in the
            daemon); the rows in the filter's memory of a doubtful fill (one the
            neighbours show to be wrong: ``GapFiller.settling``) are not used;
``oracle``  the frames stay, the filter sees the measured sample, but the row never
            updates the estimators: the cost of the sample alone;
``speed``   as ``oracle``, but the speed of the lost row on the straight line between
            its neighbours (the current measured);
``current`` as ``oracle``, but the current on the straight line (the speed measured);
``noise``   as ``line``, plus noise of the sensors' size on the filled row;
``skip``    as ``line``, and the ``--skip`` rows after each filled one (the filter's
            memory: its warm-up) do not update the estimators either.

In every variant the doubtful fills are judged from the measured neighbours (the same
gaps), their memory left out; ``--doubt inf`` judges none doubtful (as before that
rule). Printed: every parameter's difference from the twin in the twin's sigma, the
doubtful fills, and the twin's own distance from the drive's truth. The variants other
than ``line`` patch ``GapFiller.fill`` in this process only.

Usage::

    nice python tools/gap_fill_cost.py [--duration 900] [--fraction 0.008] [--seeds 1 2]
                                       [--doubt 8]
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Iterator

import numpy as np

from canrls.can.frameblock import FrameBlock
from canrls.core.samples import Signals
from canrls.estimation import selection
from canrls.processor.config import AppConfig, prepare
from canrls.processor.replay import fit_frames
from canrls.sim.scenario import Simulator, scenario

EFFECTS = "inertia,viscous,coulomb,offset,unbalance,cogging:6"
VARIANTS = ("line", "oracle", "speed", "current", "noise", "skip")
#: the simulated speed sensor's noise [rad/s] (canrls.sim: the standard scenario)
SPEED_NOISE = 0.02
#: the library's threshold of a doubtful fill [noise sigmas]
DOUBT = selection.FILL_DOUBT
#: doubtful fills of the last fit
DOUBTFUL = [0]


def fit(duration: float, seed: int, variant: str | None, fraction: float,
        skip: int, doubt: float = selection.FILL_DOUBT) -> dict[str, tuple[float, float, float]]:
    """{parameter: (value, sigma, truth)} of one run (``variant`` None: the twin)."""
    cfg = AppConfig()
    cfg.model = {"effects": EFFECTS.split(","), "kt": 0.1}
    protocol, model, settings = prepare(cfg)
    sc = scenario("standard", effects=EFFECTS, seed=seed, duration=duration,
                  excitation="standard", faults="none")
    sim = Simulator(sc)
    n = sc.periods
    rng = np.random.default_rng(1000 + seed)
    gone = np.zeros(n + 16, np.bool_)
    if variant is not None:
        gone[rng.choice(np.arange(100, n - 100), int(fraction * n), replace=False)] = True
    dt = sc.dt

    def period(t: np.ndarray) -> np.ndarray:
        return np.clip(np.rint(np.asarray(t) / dt).astype(np.int64), 0, n + 15)

    line = selection.GapFiller.fill
    measured: list[np.ndarray | None] = [None]
    noise_rng = np.random.default_rng(7 + seed)

    def fill(self: selection.GapFiller, s: Signals) -> tuple[Signals, np.ndarray | None]:
        if variant in ("oracle", "speed", "current"):  # the row stays in the filter, unused
            real = ~gone[period(s.t)]
            if real.all():
                return s, None
            if variant != "oracle":
                # one signal of the lost rows on the straight line between the measured
                # rows around (a lost row at a block's end keeps its measured value)
                k = np.arange(len(s))
                v = np.array(getattr(s, variant), dtype=np.float64)
                inner = ~real & (k > 0) & (k < len(s) - 1)
                v[inner] = np.interp(k[inner], k[real], v[real])
                s = Signals(s.t, v if variant == "current" else s.current,
                            v if variant == "speed" else s.speed, s.position, s.voltage)
            return s, real
        out, real = line(self, s)
        if real is None:
            return out, None
        if variant == "noise":
            f = ~real
            d = np.diff(s.current)
            sd_i = float(np.std(d) / math.sqrt(2)) if len(d) > 10 else 0.0
            out.speed[f] += noise_rng.normal(0.0, SPEED_NOISE, int(f.sum()))
            out.current[f] += noise_rng.normal(0.0, sd_i, int(f.sum()))
        elif variant == "skip":
            measured[0] = real  # the doubtful fills are judged on the measured rows
            real = real.copy()
            for j in np.flatnonzero(~real):
                real[j:j + skip + 1] = False
        return out, real

    def blocks() -> Iterator[FrameBlock]:
        for b in sim.frames(60000):
            if variant in ("line", "noise", "skip"):
                b = b.take(~gone[period(b.t)])  # both frames of a period
            yield b

    settling = selection.GapFiller.settling
    doubtful = [0]

    def settle(self: selection.GapFiller, s: Signals,
               real: np.ndarray | None) -> np.ndarray | None:
        before = self.doubtful
        out = settling(self, s, measured[0] if variant == "skip" and real is not None else real)
        doubtful[0] += self.doubtful - before
        return out

    selection.GapFiller.fill = fill  # type: ignore[method-assign]
    selection.GapFiller.settling = settle  # type: ignore[method-assign]
    selection.FILL_DOUBT = doubt
    try:
        res = fit_frames(blocks(), protocol, model, settings)
    finally:
        selection.GapFiller.fill = line  # type: ignore[method-assign]
        selection.GapFiller.settling = settling  # type: ignore[method-assign]
        selection.FILL_DOUBT = DOUBT
    DOUBTFUL[0] = doubtful[0]
    return {p.name: (p.value, p.sigma, float(sc.truth.get(p.name, math.nan)))
            for p in res.estimates.parameters}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=900.0, help="simulated seconds (900)")
    ap.add_argument("--fraction", type=float, default=0.008,
                    help="share of the control periods taken away (0.008)")
    ap.add_argument("--skip", type=int, default=50,
                    help="rows after a filled one not used in the 'skip' variant (50)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    ap.add_argument("--doubt", type=float, default=DOUBT,
                    help=f"threshold of a doubtful fill in noise sigmas (library: {DOUBT:g}; "
                         "inf: no fill is doubtful, as before that rule)")
    args = ap.parse_args(argv)
    if not (0.0 < args.fraction < 0.5):
        ap.error(f"--fraction {args.fraction:g}: must lie in (0, 0.5)")
    if not args.doubt > 0:
        ap.error(f"--doubt {args.doubt:g}: must be > 0")
    for seed in args.seeds:
        twin = fit(args.duration, seed, None, args.fraction, args.skip, args.doubt)
        names = list(twin)
        print(f"seed {seed}, {args.duration:g} s, {int(args.fraction * args.duration * 1000)} "
              f"single-sample gaps, doubt {args.doubt:g} sigma; faulted minus twin "
              f"[twin sigma]:")
        print("  " + " " * 8 + "".join(f"{n:>15s}" for n in names) + "   largest  doubtful")
        for v in args.variants:
            run = fit(args.duration, seed, v, args.fraction, args.skip, args.doubt)
            z = [(run[n][0] - twin[n][0]) / twin[n][1] for n in names]
            print(f"  {v:8s}" + "".join(f"{x:+15.2f}" for x in z)
                  + f"   {max(abs(x) for x in z):7.2f}  {DOUBTFUL[0]:8d}", flush=True)
        print(f"  {'twin-tru':8s}" + "".join(f"{(twin[n][0] - twin[n][2]) / twin[n][1]:+15.2f}"
                                           for n in names))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
