"""The fixed cost of a fit: ``fit_logs`` of many short logs one after another, as a fleet
worker fits them (one configuration, built once).

Prints figures; it is not a test. ``--logs`` simulated logs of ``--duration`` s
(``canrls.sim.fleet_plan``, the fleet's effects and Kt; written into ``--dir`` unless
they are there already), fitted in a fresh process after a warm-up pass over all of
them: CPU and wall time per log of each of ``--repeat`` passes, and the load average.

``--against SRC`` runs the same in the ``src`` tree of other code (another checkout,
its extensions built), the two sides interleaved in turn (this code first, then
``SRC`` twice, this code twice, ...), so that both see the same load::

    python tools/bench_fit_short.py [--logs 200] [--duration 3] [--repeat 5]
                                    [--dir DIR] [--against OTHER/src]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SRC = Path(__file__).resolve().parent.parent / "src"


def write_logs(out: Path, n: int, duration: float) -> list[str]:
    """``n`` simulated logs of ``duration`` s under ``out`` (kept when there)."""
    from canrls.sim.fleet_plan import make_fleet, write_recording

    plan = make_fleet(max(1, n // 10), 10, duration, seed=52)
    paths = []
    for drive, rec in [(d, r) for d in plan.drives for r in d.recordings][:n]:
        p = out / rec.file
        if not p.exists():
            p.parent.mkdir(parents=True, exist_ok=True)
            write_recording(p, drive, rec, duration)
        paths.append(str(p))
    return paths


def child(paths: list[str]) -> dict[str, float]:
    """One pass of ``fit_logs`` over ``paths`` after a warm-up pass: ms a log."""
    from canrls.processor.config import AppConfig, prepare
    from canrls.processor.replay import fit_logs
    from canrls.sim.fleet_plan import FLEET_EFFECTS, FLEET_KT

    cfg = AppConfig()
    cfg.model = {"effects": FLEET_EFFECTS.split(","), "kt": FLEET_KT}
    protocol, model, settings = prepare(cfg)
    for p in paths:  # the kernels loaded, the files in the page cache
        fit_logs([p], protocol, model, settings)
    load = os.getloadavg()[0]
    c, t = time.process_time(), time.perf_counter()
    for p in paths:
        fit_logs([p], protocol, model, settings)
    n = len(paths)
    return {"cpu_ms": (time.process_time() - c) / n * 1e3,
            "wall_ms": (time.perf_counter() - t) / n * 1e3, "load": load}


def run(src: Path, listing: Path) -> dict[str, float]:
    """:func:`child` in a fresh process on the code of ``src``."""
    env = {**os.environ, "PYTHONPATH": str(src)}
    out = subprocess.run([sys.executable, __file__, "--child", str(listing)], env=env,
                         check=True, capture_output=True, text=True).stdout
    return dict(json.loads(out.splitlines()[-1]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", type=int, default=200)
    ap.add_argument("--duration", type=float, default=3.0)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--dir", type=Path, default=None, help="where the logs are (kept)")
    ap.add_argument("--against", type=Path, default=None, help="the src tree of other code")
    ap.add_argument("--child", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        print(json.dumps(child(args.child.read_text().split("\n"))))
        return 0
    with tempfile.TemporaryDirectory(prefix="canrls-fit-short-") as tmp:
        out = args.dir or Path(tmp)
        paths = write_logs(out, args.logs, args.duration)
        listing = Path(tmp) / "logs.txt"
        listing.write_text("\n".join(paths))
        sides = {"this": SRC} if args.against is None else {"this": SRC,
                                                            "against": args.against}
        names = list(sides)
        got: dict[str, list[dict[str, float]]] = {k: [] for k in names}
        print(f"fit_logs of {len(paths)} logs of {args.duration:g} s, one configuration")
        for k in range(args.repeat):
            order = names if k % 2 == 0 else names[::-1]
            for name in order:
                r = run(sides[name], listing)
                got[name].append(r)
                print(f"  {k + 1:2d} {name:7s} CPU {r['cpu_ms']:6.2f} ms a log, wall "
                      f"{r['wall_ms']:6.2f} ms, load {r['load']:.1f}", flush=True)
        for name in names:
            cpu = [r["cpu_ms"] for r in got[name]]
            print(f"{name}: CPU ms a log median {statistics.median(cpu):.2f} "
                  f"(min {min(cpu):.2f}, max {max(cpu):.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
