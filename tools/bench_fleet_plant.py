"""Benchmark of ``canrls fleet`` at the size of a plant: the report of a PostgreSQL
history of ``--drives`` × ``--recordings`` (the issue's aim: 1,000 × 52 weekly
recordings, ``fleet report --json`` in ≤ 60 s and the HTML report in ≤ 120 s, ≤ 1 GB),
and ingest throughput per Dask worker against ``fit_logs`` on the same logs (aim ≥ 70 %
of its frames per second).

    .venv/bin/python tools/bench_fleet_plant.py                               # 1,000 x 52
    .venv/bin/python tools/bench_fleet_plant.py --drives 100 --logs 20        # a quick look

* **The history**: a PostgreSQL server started as the tests start it
  (``tests/helpers/postgres.py``: a throwaway cluster on a unix socket), filled with the
  parameter histories of ``tests/helpers/fleet_histories.py`` (the estimates a fit gives, with
  their sigma and the bias of each recording's excitation and length; five of every 40
  drives changing; candidate rankings on every recording) through
  :meth:`canrls.fleet.history.History.store`, 1,000 recordings a transaction.
* **The report**: ``canrls fleet report --db URL --json`` and ``--out DIR`` as commands,
  each in its own process: wall time and the process's peak resident memory.
* **Ingest** (``--logs N``, 0 to skip): N simulated logs of ``--duration`` s
  (``canrls.sim.fleet_plan``), ``fit_logs`` of each one after another in this process against
  ``canrls fleet ingest`` on a LocalCluster of one worker, side by side ``--repeat``
  times (the machine may be shared): frames per second of each, their ratio each time
  and the median ratio. ``--drives 0`` measures the ingest only.

Figures go to docs/fleet.md; nothing is asserted.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "helpers"))

from fleet_histories import simulated_fleet  # noqa: E402
from postgres import postgres_server  # noqa: E402

from canrls.fleet.history import History  # noqa: E402

PER_FLEET = 40  # drives per simulated fleet (five of them changing)
BATCH = 1000  # recordings per transaction


def fill(url: str, drives: int, recordings: int, jitter: float) -> int:
    """Store ``drives`` x ``recordings`` simulated recordings; returns how many."""
    n = 0
    rid = 1
    with History.open(url) as h:
        for k in range(0, drives, PER_FLEET):
            f = simulated_fleet(1000 + k, jitter, drives=min(PER_FLEET, drives - k),
                                recordings=recordings, start_id=rid)
            rid += len(f.recordings)
            recs = [dataclasses.replace(r, id=None, drive=f"f{k // PER_FLEET:03d}-{r.drive}")
                    for r in f.recordings]
            for i in range(0, len(recs), BATCH):
                h.store(recs[i:i + BATCH])
            n += len(recs)
    return n


def report(url: str, *args: str) -> tuple[float, float]:
    """Wall time [s] and peak RSS [MiB] of ``canrls fleet report --db URL ARGS``."""
    t = time.monotonic()
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    subprocess.run([sys.executable, "-m", "canrls", "fleet", "report", "--db", url, *args],
                   check=True, stdout=subprocess.DEVNULL)
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    if peak <= before:
        print("  (peak RSS: not above an earlier child's; read it as at most that)")
    return time.monotonic() - t, peak / 1024.0


def ingest_throughput(n: int, duration: float, out: Path, repeat: int) -> None:
    from canrls.fleet.cluster import dask_client
    from canrls.fleet.ingest import JobConfig, ingest
    from canrls.fleet.sources import LogSource
    from canrls.processor.replay import fit_logs
    from canrls.sim.fleet_plan import FLEET_EFFECTS, FLEET_KT, make_fleet, write_recording

    plan = make_fleet(max(1, n // 10), 10, duration, seed=52)
    jobs = [(d, r) for d in plan.drives for r in d.recordings][:n]
    sources = []
    for d, r in jobs:
        p = out / r.file
        p.parent.mkdir(parents=True, exist_ok=True)
        write_recording(p, d, r, duration)
        sources.append(LogSource(str(p), d.name, d.type))
    cfg = JobConfig(effects=FLEET_EFFECTS, kt=FLEET_KT)
    protocol, model, settings = cfg.prepared()
    fit_logs([sources[0].path], protocol, model, settings)  # the kernels loaded once
    frames = sum(fit_logs([s.path], protocol, model, settings).frames.total
                 for s in sources[:1])
    print(f"ingest: {len(sources)} logs of {duration:g} s")
    ratios = []
    with dask_client(None, 1) as c:
        for k in range(repeat):
            t = time.monotonic()
            frames = sum(fit_logs([s.path], protocol, model, settings).frames.total
                         for s in sources)
            serial = time.monotonic() - t
            with History.open(out / f"ingest-{k}.db") as h:
                s = ingest(sources, cfg, h, client=c)
            assert s.stored == len(sources), s.format()
            ratios.append(serial / s.elapsed_s)
            print(f"  {frames} frames: fit_logs one after another, one process "
                  f"{serial:6.2f} s {frames / serial:8.0f} frames/s; fleet ingest, "
                  f"1 worker {s.elapsed_s:6.2f} s {frames / s.elapsed_s:8.0f} frames/s "
                  f"= {ratios[-1]:.0%}", flush=True)
    print(f"  median of {repeat}: ingest per worker = {statistics.median(ratios):.0%} of "
          f"fit_logs' frames per second (the worker started once, before the first)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drives", type=int, default=1000)
    ap.add_argument("--recordings", type=int, default=52)
    ap.add_argument("--jitter", type=float, default=0.02)
    ap.add_argument("--figures", type=int, default=20, help="drives drawn in the HTML")
    ap.add_argument("--logs", type=int, default=40, help="logs for the ingest part (0: none)")
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--repeat", type=int, default=5, help="ingest measurements, side by side")
    args = ap.parse_args()
    print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory(prefix="canrls-plant-") as tmp, \
            postgres_server() as url:
        if args.drives:
            t = time.monotonic()
            n = fill(url, args.drives, args.recordings, args.jitter)
            print(f"history: {args.drives} drives x {args.recordings} recordings = {n} "
                  f"stored in PostgreSQL in {time.monotonic() - t:.1f} s")
            wall, rss = report(url, "--json")
            print(f"fleet report --json:         {wall:7.1f} s, peak RSS {rss:6.0f} MiB")
            wall, rss = report(url, "--out", str(Path(tmp) / "report"),
                               "--figures", str(args.figures))
            print(f"fleet report --out (HTML):   {wall:7.1f} s, peak RSS {rss:6.0f} MiB")
        if args.logs:
            ingest_throughput(args.logs, args.duration, Path(tmp), args.repeat)
    print(f"load average after: {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
