"""Benchmark of ``canrls fleet ingest``: recordings per minute on 1 and 2 Dask workers,
each worker's peak memory, beside fitting the same logs one after another.

    .venv/bin/python tools/bench_fleet.py                    # 50 drives x 20 recordings of 60 s
    .venv/bin/python tools/bench_fleet.py --drives 10 --recordings 5 --duration 10   # a quick look

Writes the simulated fleet (``canrls.sim.fleet_plan``, on the cluster's workers) once into
``--out`` (reused when it is there with the same settings), then prints:

* ``fit_logs`` of every log in one process, one after another (the pipeline of
  ``canrls fit`` without the command's start-up), and ``canrls fit LOG`` as a command
  for the first ``--commands`` logs (the start-up a script pays per log);
* ``canrls fleet ingest`` into a fresh SQLite history with a LocalCluster of 1 and of 2
  worker processes (and any other ``--workers``): wall time, recordings per minute,
  each worker's peak resident memory.

Figures go to docs/fleet.md; nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from canrls.fleet.cluster import dask_client
from canrls.fleet.history import History
from canrls.fleet.ingest import JobConfig, ingest
from canrls.fleet.sources import from_manifest
from canrls.processor.replay import fit_logs
from canrls.sim.fleet_plan import FLEET_EFFECTS, FLEET_KT, make_fleet, write_recording


def write(out: Path, drives: int, recordings: int, duration: float, seed: int) -> None:
    stamp = {"drives": drives, "recordings": recordings, "duration": duration, "seed": seed}
    marker = out / "bench.json"
    if marker.exists() and json.loads(marker.read_text()) == stamp:
        print(f"fleet: reusing {out}")
        return
    shutil.rmtree(out, ignore_errors=True)
    plan = make_fleet(drives, recordings, duration, seed=seed)
    jobs = [(d, r) for d in plan.drives for r in d.recordings]
    for d in plan.drives:
        (out / d.type / d.name).mkdir(parents=True, exist_ok=True)
    t = time.monotonic()
    with dask_client(None, 2) as c:
        c.gather(c.map(lambda dr: write_recording(out / dr[1].file, dr[0], dr[1], duration),
                       jobs, pure=False))
    (out / "manifest.csv").write_text(
        "path,drive,type\n" + "".join(f"{r.file},{d.name},{d.type}\n" for d, r in jobs))
    (out / "truth.json").write_text(json.dumps(plan.truth()))
    marker.write_text(json.dumps(stamp))
    size = sum(p.stat().st_size for p in out.rglob("*.log"))
    print(f"fleet: {len(jobs)} logs of {duration:g} s ({size / 2**30:.2f} GiB) written in "
          f"{time.monotonic() - t:.0f} s on 2 workers")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drives", type=int, default=50)
    ap.add_argument("--recordings", type=int, default=20)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--out", default="/tmp/canrls-bench-fleet")
    ap.add_argument("--workers", default="1,2", help="worker counts, comma-separated")
    ap.add_argument("--commands", type=int, default=20,
                    help="logs fitted by 'canrls fit' as a command, one process each")
    args = ap.parse_args()
    out = Path(args.out)
    write(out, args.drives, args.recordings, args.duration, args.seed)
    sources = from_manifest(out / "manifest.csv")
    n = len(sources)
    cfg = JobConfig(effects=FLEET_EFFECTS, kt=FLEET_KT)
    protocol, model, settings = cfg.prepared()
    print(f"\n{n} recordings of {args.duration:g} s, model {FLEET_EFFECTS} kt={FLEET_KT}; "
          f"{os.cpu_count()} cores")

    fit_logs([sources[0].path], protocol, model, settings)  # the kernels loaded once
    t = time.monotonic()
    for s in sources:
        fit_logs([s.path], protocol, model, settings)
    serial = time.monotonic() - t
    print(f"fit_logs one after another, one process: {serial:7.1f} s  "
          f"{n / serial * 60:7.0f} recordings/min")
    k = min(args.commands, n)
    if k:
        t = time.monotonic()
        for s in sources[:k]:
            subprocess.run([sys.executable, "-m", "canrls", "fit", s.path, "--effects",
                            FLEET_EFFECTS, "--kt", str(FLEET_KT), "--quiet"],
                           check=True, capture_output=True)
        per = (time.monotonic() - t) / k
        print(f"canrls fit LOG as a command ({k} logs):     {per:7.2f} s each "
              f"{60 / per:7.0f} recordings/min (so {n * per:.0f} s for all {n})")

    for w in (int(x) for x in args.workers.split(",") if x.strip()):
        db = out / f"bench-{w}.db"
        for p in out.glob(f"bench-{w}.db*"):
            p.unlink()
        t = time.monotonic()
        with dask_client(None, w) as c:
            started = time.monotonic() - t
            with History.open(db) as h:
                s = ingest(sources, cfg, h, client=c)
        total = time.monotonic() - t
        assert s.stored == n, s.format()
        peaks = ", ".join(f"{v / 2**20:.0f}" for v in sorted(s.worker_peak_rss.values()))
        print(f"fleet ingest, {w} worker{'s' if w > 1 else ' '}: {s.elapsed_s:7.1f} s  "
              f"{n / s.elapsed_s * 60:7.0f} recordings/min  (cluster start {started:.1f} s, "
              f"with it {n / total * 60:.0f}/min); peak RSS per worker [MiB]: {peaks}; "
              f"fit_logs one after another / workers: {serial / w:.1f} s")
        db.unlink()


if __name__ == "__main__":
    main()
