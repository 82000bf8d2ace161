"""Benchmark of ``canrls fleet`` at the size of a plant: the report of a PostgreSQL
history of ``--drives`` × ``--recordings`` (the issue's aim: 1,000 × 52 weekly
recordings, ``fleet report --json`` in ≤ 60 s and the HTML report in ≤ 120 s, ≤ 1 GB),
the plant's ingest itself, and ingest throughput per Dask worker against ``fit_logs``
on the same logs (aim ≥ 70 % of its frames per second).

    .venv/bin/python tools/bench_fleet_plant.py --logs 0                      # the report
    .venv/bin/python tools/bench_fleet_plant.py --drives 0 --plant-drives 1000 --logs 0
    .venv/bin/python tools/bench_fleet_plant.py --drives 0 --logs 40 --repeat 15

* **The history**: a PostgreSQL server started as the tests start it
  (``tests/helpers/postgres.py``: a throwaway cluster on a unix socket), filled with the
  parameter histories of ``tests/helpers/fleet_histories.py`` (the estimates a fit gives, with
  their sigma and the bias of each recording's excitation and length; five of every 40
  drives changing; candidate rankings on every recording) through
  :meth:`canrls.fleet.history.History.store`, 1,000 recordings a transaction.
* **The report**: ``canrls fleet report --db URL --json`` and ``--out DIR`` as commands,
  each in its own process: wall time and the command's peak resident memory.
* **The plant's ingest** (``--plant-drives D``, 0 to skip): ``canrls.sim.fleet_plan`` plans D
  drives × ``--plant-weeks`` weekly logs of ``--plant-duration`` s (3 s by default:
  short logs, so that the cost is the pipeline's per log rather than the frames'),
  written into a temporary directory (a process pool of ``--workers``) and ingested by
  ``canrls fleet ingest`` as a command on a LocalCluster of ``--workers`` into a fresh
  PostgreSQL server; then both reports of that history. A pilot first (``--pilot``
  drives × 2 weeks, on its own server) measures the cost per log; the whole runs only
  if writing and ingesting it project to at most ``--budget`` s (20 minutes), else the
  most weeks of every drive that do, and the projection is printed.
* **Ingest throughput** (``--logs N``, 0 to skip): N simulated logs of ``--duration`` s,
  ``fit_logs`` of each one after another in this process against ``canrls fleet
  ingest`` on a LocalCluster of one warm worker, ``--repeat`` pairs, the side that goes
  first alternating (the machine may be shared): frames per second of each, their
  ratio, and the CPU of the loop against the worker's; the median, quartiles and range
  of both ratios and the load average while it ran.

Figures go to docs/fleet.md; nothing is asserted.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

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


#: runs a command and prints its peak RSS [KiB] last on stderr: a fresh process per
#: command, so that the figure is that command's alone
_PEAK = ("import resource, subprocess, sys; r = subprocess.run(sys.argv[1:]); "
         "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr); "
         "sys.exit(r.returncode)")


class _Load:
    """The 1-minute load average sampled every ``every`` s while a ``with`` block runs:
    ``str()`` gives its range."""

    def __init__(self, every: float = 10.0) -> None:
        self.every = every
        self.seen = [os.getloadavg()[0]]
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._sample, daemon=True)

    def _sample(self) -> None:
        while not self.stop.wait(self.every):
            self.seen.append(os.getloadavg()[0])

    def __enter__(self) -> _Load:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join()
        self.seen.append(os.getloadavg()[0])

    def __str__(self) -> str:
        return (f"load {min(self.seen):.1f}-{max(self.seen):.1f} "
                f"(median {statistics.median(self.seen):.1f})")


def _measured(*args: str) -> tuple[float, float, str]:
    """Wall time [s], peak RSS [MiB] and output of ``canrls ARGS`` as a command."""
    t = time.monotonic()
    res = subprocess.run([sys.executable, "-c", _PEAK, sys.executable, "-m", "canrls", *args],
                         capture_output=True, text=True)
    if res.returncode:
        raise SystemExit(f"canrls {' '.join(args)}: exit {res.returncode}: {res.stderr}")
    return time.monotonic() - t, int(res.stderr.split()[-1]) / 1024.0, res.stdout


def report(url: str, *args: str) -> tuple[float, float]:
    """Wall time [s] and peak RSS [MiB] of ``canrls fleet report --db URL ARGS``."""
    wall, rss, _ = _measured("fleet", "report", "--db", url, *args)
    return wall, rss


def _cpu() -> float:
    """CPU seconds of this process (every thread) so far."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _quartiles(xs: list[float]) -> str:
    q = statistics.quantiles(xs, n=4) if len(xs) > 1 else [xs[0]] * 3
    return (f"median {statistics.median(xs):.0%}, quartiles {q[0]:.0%}-{q[2]:.0%}, "
            f"range {min(xs):.0%}-{max(xs):.0%}")


def ingest_throughput(n: int, duration: float, out: Path, repeat: int) -> None:
    """``fit_logs`` of each log one after another in this process against ``canrls
    fleet ingest`` on one warm worker, ``repeat`` pairs, the side that goes first
    alternating: the ratio of frames per second (wall) and of CPU per log."""
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
    frames = sum(fit_logs([s.path], protocol, model, settings).frames.total
                 for s in sources)  # the kernels loaded, the files in the page cache
    print(f"ingest: {len(sources)} logs of {duration:g} s, {frames} frames; {repeat} pairs, "
          f"the first side alternating")
    wall: list[float] = []
    cpu: list[float] = []
    loads: list[float] = []

    def loop() -> tuple[float, float]:
        c0, t = _cpu(), time.monotonic()
        for s in sources:
            fit_logs([s.path], protocol, model, settings)
        return time.monotonic() - t, _cpu() - c0

    with dask_client(None, 1) as c:
        with History.open(out / "warm.db") as h:  # the worker's imports and model
            ingest(sources[:2], cfg, h, client=c)
        for k in range(repeat):
            loads.append(os.getloadavg()[0])
            if k % 2:
                serial, serial_cpu = loop()
            w0, c0 = sum(c.run(_cpu).values()), _cpu()
            with History.open(out / f"ingest-{k}.db") as h:
                s = ingest(sources, cfg, h, client=c)
            worker_cpu, client_cpu = sum(c.run(_cpu).values()) - w0, _cpu() - c0
            if k % 2 == 0:
                serial, serial_cpu = loop()
            assert s.stored == len(sources), s.format()
            wall.append(serial / s.elapsed_s)
            cpu.append(serial_cpu / worker_cpu)
            print(f"  {k + 1:2d} ({'loop' if k % 2 else 'ingest'} first, load "
                  f"{loads[-1]:4.1f}): fit_logs {serial:5.2f} s {frames / serial:8.0f} "
                  f"frames/s, ingest {s.elapsed_s:5.2f} s {frames / s.elapsed_s:8.0f} "
                  f"frames/s = {wall[-1]:4.0%}; CPU {serial_cpu:4.2f} s against the "
                  f"worker's {worker_cpu:4.2f} s = {cpu[-1]:4.0%} (client "
                  f"{client_cpu:4.2f} s)", flush=True)
    loads.append(os.getloadavg()[0])
    print(f"  ingest per worker / fit_logs, frames per second (wall): {_quartiles(wall)}")
    print(f"  the same in CPU per log (the worker's alone): {_quartiles(cpu)}")
    print(f"  load average {min(loads):.1f}-{max(loads):.1f} while it ran")


def _write(job: tuple[str, Any, Any, float]) -> int:
    """One simulated log (a process pool's task): its frames."""
    from canrls.sim.fleet_plan import write_recording

    path, drive, rec, duration = job
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return write_recording(path, drive, rec, duration)


def _generate(plan: Any, weeks: range, root: Path, pool: Any) -> tuple[int, float]:
    """Write the recordings ``weeks`` of every drive of ``plan`` under ``root``;
    returns (logs, seconds)."""
    jobs = [(str(root / r.file), d, r, plan.duration) for d in plan.drives
            for r in d.recordings[weeks.start:weeks.stop]]
    t = time.monotonic()
    list(pool.map(_write, jobs, chunksize=16))
    return len(jobs), time.monotonic() - t


def _ingest_cli(url: str, root: Path, workers: int) -> tuple[float, float, dict[str, Any]]:
    """``canrls fleet ingest 'ROOT/{type}/{drive}/*.log' --db URL --workers N --json``
    as a command: wall time [s], the client's peak RSS [MiB] and its summary."""
    from canrls.sim.fleet_plan import FLEET_EFFECTS, FLEET_KT

    wall, rss, out = _measured("fleet", "ingest", str(root / "{type}" / "{drive}" / "*.log"),
                               "--kt", str(FLEET_KT), "-e", FLEET_EFFECTS, "--db", url,
                               "--workers", str(workers), "--quiet", "--json")
    return wall, rss, json.loads(out)


def plant_ingest(url: str, drives: int, weeks: int, duration: float, workers: int,
                 budget: float, pilot: int, tmp: Path) -> None:
    """The plant's ingest into the history at ``url``: ``drives`` x ``weeks`` simulated
    logs of ``duration`` s, written under ``tmp`` and ingested by ``canrls fleet ingest``
    on a LocalCluster of ``workers``. A pilot (``pilot`` drives x 2 weeks, its own
    server) measures the cost per log first; the whole runs only if writing and
    ingesting it project to at most ``budget`` s, else the most weeks that do."""
    from concurrent.futures import ProcessPoolExecutor

    from canrls.sim.fleet_plan import make_fleet

    t = time.monotonic()
    plan = make_fleet(drives, weeks, duration, seed=2026)
    print(f"plant ingest: {drives} drives x {weeks} weekly logs of {duration:g} s planned "
          f"in {time.monotonic() - t:.1f} s")
    with ProcessPoolExecutor(workers) as pool:
        small = dataclasses.replace(plan, drives=plan.drives[:pilot])
        n, gen = _generate(small, range(0, 2), tmp / "pilot", pool)
        with postgres_server() as pilot_url:
            wall, rss, summary = _ingest_cli(pilot_url, tmp / "pilot", workers)
        shutil.rmtree(tmp / "pilot")
        # the command's start (imports, the cluster) once; each log the ingest's own time
        own = summary["elapsed_s"]
        per_log = (gen + own) / n
        print(f"  pilot {n} logs: written in {gen:.1f} s ({1e3 * gen / n:.0f} ms a log), "
              f"ingested in {own:.1f} s ({1e3 * own / n:.0f} ms a log, {workers} workers; "
              f"the command {wall:.1f} s), {summary['stored']} stored, load "
              f"{os.getloadavg()[0]:.1f}")
        total = drives * weeks
        start = wall - own
        fit = max(1, min(weeks, int((budget - start) / (drives * per_log))))
        print(f"  projected for {drives} x {weeks} = {total} logs: "
              f"{(total * per_log + start) / 60:.0f} min ({total * gen / n / 60:.0f} min "
              f"writing, {(total * own / n + start) / 60:.0f} min ingesting); within "
              f"{budget / 60:.0f} min: "
              + ("the whole" if fit == weeks else f"{drives} x {fit} weeks"), flush=True)
        n, gen = _generate(plan, range(0, fit), tmp / "plant", pool)
    print(f"  {n} logs written in {gen:.0f} s ({1e3 * gen / n:.0f} ms a log), load "
          f"{os.getloadavg()[0]:.1f}", flush=True)
    with _Load() as load:
        wall, rss, summary = _ingest_cli(url, tmp / "plant", workers)
    peaks = ", ".join(f"{v / 2**20:.0f}" for v in summary["worker_peak_rss"].values())
    print(f"  fleet ingest of {n} logs into PostgreSQL, {workers} workers: {wall:.0f} s "
          f"({1e3 * wall / n:.0f} ms a log; the ingest itself {summary['elapsed_s']:.0f} s, "
          f"{1e3 * summary['elapsed_s'] / n:.1f} ms a log), {summary['stored']} stored, "
          f"{summary['errors']} errors, {len(summary['failed'])} failed, client peak RSS "
          f"{rss:.0f} MiB, workers' {peaks} MiB, {load}", flush=True)
    shutil.rmtree(tmp / "plant")


def reports(url: str, tmp: Path, figures: int) -> None:
    """``fleet report --json`` and the HTML report of the history at ``url``."""
    with _Load(2.0) as load:
        wall, rss = report(url, "--json")
    print(f"fleet report --json:         {wall:7.1f} s, peak RSS {rss:6.0f} MiB, {load}",
          flush=True)
    with _Load(2.0) as load:
        wall, rss = report(url, "--out", str(tmp / "report"), "--figures", str(figures))
    print(f"fleet report --out (HTML):   {wall:7.1f} s, peak RSS {rss:6.0f} MiB, {load}",
          flush=True)
    shutil.rmtree(tmp / "report", ignore_errors=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drives", type=int, default=1000,
                    help="drives of the history filled directly, for the report (0: none)")
    ap.add_argument("--recordings", type=int, default=52)
    ap.add_argument("--jitter", type=float, default=0.02)
    ap.add_argument("--figures", type=int, default=20, help="drives drawn in the HTML")
    ap.add_argument("--plant-drives", type=int, default=0,
                    help="drives of the plant's ingest (0: none; the issue's 1000)")
    ap.add_argument("--plant-weeks", type=int, default=52)
    ap.add_argument("--plant-duration", type=float, default=3.0,
                    help="seconds of each of the plant's logs (short: the fit's cost)")
    ap.add_argument("--workers", type=int, default=2, help="workers of the plant's ingest")
    ap.add_argument("--budget", type=float, default=1200.0,
                    help="seconds the plant's logs may take to write and ingest")
    ap.add_argument("--pilot", type=int, default=100, help="drives of the pilot (x 2 weeks)")
    ap.add_argument("--logs", type=int, default=40, help="logs for the throughput (0: none)")
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--repeat", type=int, default=15, help="throughput pairs, side by side")
    args = ap.parse_args()
    print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory(prefix="canrls-plant-") as tmp:
        if args.drives:
            with postgres_server() as url:
                t = time.monotonic()
                n = fill(url, args.drives, args.recordings, args.jitter)
                print(f"history: {args.drives} drives x {args.recordings} recordings = {n} "
                      f"stored in PostgreSQL in {time.monotonic() - t:.1f} s", flush=True)
                reports(url, Path(tmp), args.figures)
        if args.plant_drives:
            with postgres_server() as url:
                plant_ingest(url, args.plant_drives, args.plant_weeks, args.plant_duration,
                             args.workers, args.budget, args.pilot, Path(tmp))
                reports(url, Path(tmp), args.figures)
        if args.logs:
            ingest_throughput(args.logs, args.duration, Path(tmp), args.repeat)
    print(f"load average after: {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
