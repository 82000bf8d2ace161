"""How well ``canrls fleet`` tells wear from weather on simulated parameter histories.

    .venv/bin/python tools/fleet_weather.py --seeds 101-110
    .venv/bin/python tools/fleet_weather.py --seeds 1-10 --gaussian --jitter 0.05

The histories come from ``tests/helpers/fleet_histories.py`` (40 drives x 10 weekly recordings,
each with its own excitation and length, friction jittering week to week, five drives
changing); :func:`canrls.fleet.detect.assess` assesses each. Prints per jitter the
changing drives alerted with the right parameter or effect, the healthy drives
alerted, and the first few misses and false alerts. Figures go to docs/fleet.md;
nothing is asserted.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "helpers"))

from fleet_histories import simulated_fleet  # noqa: E402

from canrls.fleet.detect import assess  # noqa: E402
from fleet_detection import seeds  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="101-110")
    ap.add_argument("--jitter", type=float, action="append",
                    help="week-to-week jitter of the friction (default 0, 0.01, 0.02, 0.05)")
    ap.add_argument("--gaussian", action="store_true",
                    help="the jitter a normal of that standard deviation, not uniform ±")
    args = ap.parse_args()
    for jitter in args.jitter or [0.0, 0.01, 0.02, 0.05]:
        t0 = time.perf_counter()
        found = changing = false = healthy = 0
        notes: list[str] = []
        for seed in seeds(args.seeds):
            f = simulated_fleet(seed, jitter, gaussian=args.gaussian)
            fa = assess(f.recordings)
            for d, (what, onset) in f.changing.items():
                changing += 1
                a = fa.drive(d).headline
                ok = a is not None and (a.effect == what if a.kind == "new effect"
                                        else a.series == what)
                found += ok
                if not ok:
                    notes.append(f"  missed seed {seed} {d}: {what} from recording "
                                 f"{onset + 1} (largest |z| {fa.drive(d).max_z:.1f})")
            for d in f.healthy:
                healthy += 1
                if fa.drive(d).alerts:
                    false += 1
                    notes.append(f"  false seed {seed} {d}: {fa.drive(d).alerts[0].message}")
        print(f"jitter {'sd' if args.gaussian else '±'}{100 * jitter:g} %: {found}/{changing} "
              f"changing drives alerted right, {false}/{healthy} healthy drives alerted "
              f"({time.perf_counter() - t0:.1f} s)")
        print("\n".join(notes[:6]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
