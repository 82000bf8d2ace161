"""How often sigma covers the truth: fits of the simulated drive with the right model.

For every excitation, duration and seed, the simulated drive's frames go through the
same pipeline as ``canrls fit`` and each parameter is compared with the truth. Printed:
the share of parameters within 2 sigma by parameter, by excitation and by duration
(identifiable ones; those the data cannot identify are counted apart, they make no
claim), the worst cases, and the fixed point against the float.

    .venv/bin/python tools/bench_coverage.py                      # 2 s .. 10 min, 3 seeds
    .venv/bin/python tools/bench_coverage.py --durations 2,20 --seeds 2 --jobs 2
"""

from __future__ import annotations

import argparse
import itertools
import math
import time
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

from canrls.processor.config import AppConfig, prepare
from canrls.processor.replay import fit_frames
from canrls.sim.scenario import Simulator, scenario

EXCITATIONS = ("standard", "steps", "prbs", "chirp", "slow")
DURATIONS = (2.0, 5.0, 20.0, 60.0, 600.0)
EFFECTS = ("inertia", "viscous", "coulomb")


@dataclass(frozen=True)
class Row:
    """One parameter of one fit."""

    excitation: str
    duration: float
    seed: int
    parameter: str
    z: float            # (estimate - truth) / sigma
    error: float        # relative to the truth
    fixed: float        # (fixed - float) / |float|
    identifiable: bool


def fit_one(case: tuple[str, float, int]) -> list[Row]:
    """Simulate one run and fit it with the right model."""
    excitation, duration, seed = case
    sc = scenario("standard", excitation=excitation, duration=duration, seed=seed)
    cfg = AppConfig()
    cfg.model["kt"] = sc.truth.kt
    cfg.model["effects"] = list(EFFECTS)
    protocol, model, settings = prepare(cfg)
    res = fit_frames(Simulator(sc).frames(), protocol, model, settings)
    rows = []
    for p in res.parameters:
        truth = sc.truth.params[p.name]
        rows.append(Row(excitation, duration, seed, p.name,
                        (p.value - truth) / p.sigma if p.sigma > 0 else math.inf,
                        (p.value - truth) / truth,
                        (p.fixed - p.value) / abs(p.value) if p.value else math.nan,
                        p.identifiable))
    return rows


def coverage(rows: list[Row], key: str) -> dict[object, tuple[float, int, int]]:
    """``{group: (share within 2 sigma, identifiable rows, rows not identifiable)}``."""
    groups: dict[object, list[Row]] = defaultdict(list)
    for r in rows:
        groups[getattr(r, key)].append(r)
    out = {}
    for g, rs in groups.items():
        ident = [r for r in rs if r.identifiable]
        inside = sum(abs(r.z) <= 2.0 for r in ident)
        out[g] = (inside / len(ident) if ident else math.nan, len(ident), len(rs) - len(ident))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--excitations", default=",".join(EXCITATIONS))
    ap.add_argument("--durations", default=",".join(f"{d:g}" for d in DURATIONS))
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args()
    cases = list(itertools.product(a.excitations.split(","),
                                   [float(d) for d in a.durations.split(",")],
                                   range(1, a.seeds + 1)))
    # the long runs first, so that the workers finish together
    cases.sort(key=lambda c: -c[1])
    t0 = time.perf_counter()
    with ProcessPoolExecutor(a.jobs) as pool:
        rows = [r for rs in pool.map(fit_one, cases) for r in rs]
    wall = time.perf_counter() - t0
    print(f"{len(cases)} fits, {len(rows)} parameters, {wall:.0f} s wall ({a.jobs} jobs)")
    for key in ("parameter", "excitation", "duration"):
        print(f"\nwithin 2 sigma, by {key} (identifiable; not identifiable apart):")
        for g, (share, n, weak) in coverage(rows, key).items():
            print(f"  {g!s:<12} {100 * share:5.1f} %  of {n:3d}"
                  + (f"   ({weak} not identifiable)" if weak else ""))
    ident = [r for r in rows if r.identifiable]
    allc = sum(abs(r.z) <= 2.0 for r in ident) / len(ident) if ident else math.nan
    print(f"\nall: {100 * allc:.1f} % of {len(ident)} within 2 sigma "
          f"({len(rows) - len(ident)} not identifiable)")
    worst = sorted(ident, key=lambda r: -abs(r.z))[:8]
    print("\nlargest |estimate - truth| / sigma:")
    for r in worst:
        print(f"  {r.excitation:<9} {r.duration:5g} s seed {r.seed}  {r.parameter:<11} "
              f"{r.z:+6.2f} sigma  ({100 * r.error:+.3f} % of the truth)")
    fx = [abs(r.fixed) for r in ident if math.isfinite(r.fixed)]
    if fx:
        print(f"\nfixed point against float: largest {100 * max(fx):.2g} % "
              f"(median {100 * sorted(fx)[len(fx) // 2]:.2g} %)")


if __name__ == "__main__":
    main()
