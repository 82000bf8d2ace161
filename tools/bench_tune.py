"""Ripple reduction and bandwidth error of ``canrls tune`` over random simulated drives.

Each drive: parameters within +-50 % of the default drive, one cogging order from 4 to 48;
a 20 s log of ordinary motion (the standard excitation) through ``canrls sim``, the
map and the gains of ``canrls tune`` on it (bandwidth 20 Hz, the simulator's delay of half
a period), then in closed loop: the speed ripple at 5 rad/s without and with the map, and
the bandwidth measured from speed steps (20 <-> 30 rad/s, map and gains loaded). Prints
one row per drive, the median and the worst (docs/tune.md)::

    python tools/bench_tune.py --drives 20 --seed 1
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

from canrls.cli.main import main
from canrls.cli.sim import with_tuning
from canrls.sim.excitation import constant
from canrls.sim.loop import speed_ripple, step_bandwidth
from canrls.sim.plant import Plant
from canrls.sim.scenario import Simulator, default_params, scenario

BANDWIDTH = 20.0


def quiet(argv: list[str]) -> None:
    """``canrls ARGV`` in this process, its output swallowed; a failure stops the run."""
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        rc = main(argv)
    if rc != 0:
        raise SystemExit(f"canrls {' '.join(argv)}: exit status {rc}")


def one_drive(rng: np.random.Generator, tmp: Path) -> dict[str, float]:
    k = int(rng.integers(4, 49))
    effects = f"inertia,viscous,coulomb,stribeck,cogging:{k}"
    params = {name: v * float(rng.uniform(0.5, 1.5))
              for name, v in default_params(effects).items()}
    log, out = tmp / "drive.log", tmp / "out"
    p = [x for n, v in params.items() for x in ("-p", f"{n}={v!r}")]
    quiet(["sim", "--out", str(log), "--duration", "20", "--effects", effects, "--seed",
           str(int(rng.integers(1 << 30))), *p])
    quiet(["tune", str(log), "--kt", "0.1", "-e", effects, "--bandwidth", str(BANDWIDTH),
           "--delay", "0.5", "--out", str(out)])

    def ripple(ff: Path | None) -> float:
        sc = scenario("standard", effects=effects, params=params, excitation=constant(5.0),
                      duration=8.0, seed=3)
        ch = Simulator(with_tuning(sc, None if ff is None else str(ff), None)).step(sc.periods)
        return speed_ripple(ch.measured.position[3000:], ch.measured.speed[3000:],
                            orders=max(24, 2 * k))

    before, after = ripple(None), ripple(out / "feedforward.json")
    # the steps with the map and the gains loaded, as on the rig (the cogging's ripple
    # would otherwise sit in the step response: order 6 at 25 rad/s is 24 Hz)
    sc = with_tuning(scenario("standard", effects=effects, params=params),
                     str(out / "feedforward.json"), str(out / "gains.json"))
    plant = Plant(sc.truth, sc.dt, sc.controller, sc.sensors, seed=5)
    bw = step_bandwidth(plant, 20.0, 30.0)
    torque = json.loads((out / "feedforward.json").read_text())["ripple"]
    return {"order": k, "J": params["inertia.J"], "before": before, "after": after,
            "reduction": 1.0 - after / before, "torque_reduction": torque["reduction"],
            "bandwidth": bw, "bw_error": bw / BANDWIDTH - 1.0}


def main_(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--drives", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    rows = []
    print(f"{'drive':>5} {'order':>5} {'J':>9} {'ripple before':>13} {'after':>9} "
          f"{'reduction':>9} {'bandwidth':>9} {'error':>7}")
    with tempfile.TemporaryDirectory() as d:
        for i in range(args.drives):
            r = one_drive(rng, Path(d))
            rows.append(r)
            print(f"{i:5d} {r['order']:5d} {r['J']:9.3g} {r['before']:13.4g} "
                  f"{r['after']:9.3g} {100 * r['reduction']:8.1f}% {r['bandwidth']:8.2f}Hz "
                  f"{100 * r['bw_error']:+6.1f}%", flush=True)
    red = np.array([r["reduction"] for r in rows])
    err = np.array([abs(r["bw_error"]) for r in rows])
    print(f"speed ripple at 5 rad/s reduced: median {100 * np.median(red):.1f} %, worst "
          f"{100 * red.min():.1f} %")
    print(f"bandwidth error (requested {BANDWIDTH:g} Hz): median {100 * np.median(err):.1f} %, "
          f"worst {100 * err.max():.1f} %")
    return 0 if math.isfinite(float(err.max())) else 1


if __name__ == "__main__":
    sys.exit(main_())
