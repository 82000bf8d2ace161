"""End-to-end offline replay throughput, against the loop a user would write by hand.

Prints figures; it is not a test. On a candump log of the simulated drive (1 kHz,
two frames per period: ten minutes are 1.2 M frames; times from an epoch, as
``candump -l`` writes them), in one run:

* ``canrls fit LOG`` as a whole process (``--repeat`` runs after an untimed one, which
  also writes the package's bytecode as a user's first run does): wall and CPU time,
  min / median / max, and frames per second of the median -- the figure the goal
  (>= 2 M frames/s, the process's start-up included) is about;
* canrls inside one process, each the best of ``--repeat`` runs after a warm-up (the
  first read of the file is not timed):

  - ``read_frames`` alone (parse the candump text into frame blocks),
  - read + strict decode + pairing (``FrameProcessor.samples``),
  - ``fit_log``: read, decode, pair, regressors, float and fixed-point RLS;
  - ``write_candump`` re-writing the frames read (the read time subtracted), and
    whether that gives the log back byte for byte;

* the straightforward loop: ``can.LogReader`` -> ``cantools`` ``decode_message`` ->
  pairing by alive counter in a dict -> regressors per sample in Python ->
  ``padasip.filters.FilterRLS.adapt``. It does less than canrls (no CRC or counter
  checks, finite differences instead of the state-variable filter, float only, no
  fixed point), so the ratio is on the low side. It runs on the first
  ``--naive-frames`` frames and is extrapolated to the whole log (said in the output),
  and the whole process of ``canrls fit`` is compared with it (goal: >= 30 times);

* peak RSS (``resource.getrusage``) of a fresh process that runs ``prepare`` and
  ``fit_log`` on a log of ``duration / 6`` and on the full log, and its RSS before
  the replay: the same figure for both shows that memory is flat in the log's length.

Times are wall clock; the process CPU time is printed beside each, since the machine
may be shared (CPU time leaves out the time the process waited for a core).

The log is generated with :mod:`canrls.sim` (``Simulator`` chunks written by
``write_candump``, the write timed on its own, the times moved by ``--epoch``) and
cached, by duration, seed, epoch and effects, under the system's temporary directory
(or ``--log``).

Usage::

    python tools/bench_replay.py [--duration 600] [--epoch 1.7e9] [--log PATH] [--seed 2]
                                 [--effects inertia,viscous,...] [--naive-frames 100000]
                                 [--repeat 3] [--chunk-size 65536] [--no-memory]
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from canrls.can.frameblock import FrameBlock
from canrls.can.logs import read_frames, write_candump
from canrls.processor import FrameProcessor
from canrls.processor.config import AppConfig, prepare
from canrls.processor.replay import fit_log

EFFECTS = "inertia,viscous,coulomb,offset,unbalance,cogging:6"
KT = 0.1  # the standard scenario's torque constant [N·m/A]
EPOCH = 1.7e9  # the start of the log's times [s]: candump -l writes epoch times
GOAL_WHOLE = 2e6  # frames/s of `canrls fit`, the whole process
GOAL_RATIO = 30.0  # times the naive loop


# ------------------------------------------------------------------------------ log
def log_path(duration: float, seed: int, effects: str, epoch: float = 0.0) -> Path:
    """Where the generated log of these settings is cached."""
    tag = hashlib.sha1(effects.encode()).hexdigest()[:8]
    at = f"-at{epoch:g}" if epoch else ""
    return (Path(tempfile.gettempdir())
            / f"canrls-bench-{duration:g}s{at}-seed{seed}-{tag}.log")


def ensure_log(path: Path, duration: float, seed: int, effects: str,
               epoch: float = 0.0) -> None:
    """Simulate the drive and write its candump log (times from ``epoch``), unless
    ``path`` exists."""
    if path.exists():
        print(f"log: {path} (cached, {path.stat().st_size / 1e6:.0f} MB)")
        return
    from canrls.sim.scenario import Simulator, scenario

    sc = scenario("standard", effects=effects, duration=duration, seed=seed)
    sim = Simulator(sc)
    sim_time = [0.0]

    def blocks() -> Iterator[FrameBlock]:
        it = sim.frames(65536)
        while True:
            t0 = time.perf_counter()
            b = next(it, None)
            sim_time[0] += time.perf_counter() - t0
            if b is None:
                return
            yield dataclasses.replace(b, t=b.t + epoch) if epoch else b

    t0 = time.perf_counter()
    n = write_candump(path, blocks())
    total = time.perf_counter() - t0
    write = total - sim_time[0]
    print(f"log: {path} generated: {n} frames, {path.stat().st_size / 1e6:.0f} MB in "
          f"{total:.1f} s (simulation {sim_time[0]:.1f} s, write_candump {write:.1f} s = "
          f"{n / write / 1e6:.2f} M frames/s)")


def configure(path: Path, effects: str) -> tuple[Any, Any, Any]:
    """Protocol, model and settings as ``canrls fit`` builds them (the front end then
    calibrates on the log's first seconds: no pass over the log beforehand)."""
    cfg = AppConfig()
    cfg.model = {"effects": effects.split(","), "kt": KT}
    return prepare(cfg)


# -------------------------------------------------------------------------- timing
def best_of(fn: Callable[[], Any], repeat: int) -> tuple[float, float, Any]:
    """(best wall time, CPU time of that run, result) over ``repeat`` runs after a warm-up."""
    out = fn()
    best = (math.inf, math.inf)
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        w, c = time.perf_counter() - w0, time.process_time() - c0
        if w < best[0]:
            best = (w, c)
    return best[0], best[1], out


def line(what: str, frames: int, wall: float, cpu: float) -> str:
    return (f"  {what:<44} {wall:7.2f} s  {frames / wall / 1e6:5.2f} M frames/s"
            f"   (CPU {cpu:6.2f} s, {frames / cpu / 1e6:5.2f} M frames/s)")


def bench_whole(path: Path, effects: str, repeat: int) -> tuple[int, float]:
    """``canrls fit LOG`` as a user runs it, a fresh process each time; returns (frames,
    median wall time). The first run is not timed; it also writes the package's bytecode
    (``$PYTHONDONTWRITEBYTECODE`` is dropped), which an installation has."""
    cmd = [sys.executable, "-m", "canrls", "fit", str(path), "--kt", str(KT), "--effects",
           effects, "--json", "--quiet"]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    out = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True).stdout
    frames = int(json.loads(out)["frames"]["total"])
    walls, cpus = [], []
    for _ in range(repeat):
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        w0 = time.perf_counter()
        subprocess.run(cmd, env=env, check=True, capture_output=True)
        walls.append(time.perf_counter() - w0)
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpus.append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)

    def mmm(x: list[float]) -> str:
        return f"{min(x):5.2f} / {statistics.median(x):5.2f} / {max(x):5.2f} s"

    wall = statistics.median(walls)
    print(f"canrls fit, the whole process ({' '.join(cmd[1:3])} ... --json --quiet; "
          f"{repeat} runs, min / median / max):")
    print(f"  wall {mmm(walls)}   CPU {mmm(cpus)}")
    print(f"  {frames} frames: {frames / wall / 1e6:.2f} M frames/s on the median wall "
          f"clock ({frames / min(walls) / 1e6:.2f} at best; "
          f"{frames / statistics.median(cpus) / 1e6:.2f} per CPU second); goal "
          f">= {GOAL_WHOLE / 1e6:g} M frames/s: "
          f"{'met' if frames / wall >= GOAL_WHOLE else 'NOT met'}")
    return frames, wall


def bench_canrls(path: Path, effects: str, repeat: int,
                 chunk_size: int) -> tuple[int, float, float]:
    """Time the canrls stages; returns (frames, wall, CPU) of ``fit_log``."""
    protocol, model, settings = configure(path, effects)

    def read() -> int:
        return sum(len(b) for b in read_frames(path, chunk_size))

    def samples() -> int:
        proc = FrameProcessor(protocol, model, settings)
        n = sum(len(proc.samples(b)) for b in read_frames(path, chunk_size))
        return n + len(proc.flush_samples())

    def fit() -> Any:
        return fit_log(path, protocol, model, settings, chunk_size=chunk_size)

    print(f"canrls (best of {repeat}, chunk_size {chunk_size}; wall clock, CPU time in "
          f"brackets):")
    wall, cpu, frames = best_of(read, repeat)
    print(line("read_frames", frames, wall, cpu))
    wall, cpu, n_samples = best_of(samples, repeat)
    print(line("read + decode + pair", frames, wall, cpu))
    wall, cpu, res = best_of(fit, repeat)
    print(line("fit_log: read, decode, pair, regress, RLS", frames, wall, cpu))
    print(f"  ({res.frames.total} frames, {n_samples} samples, {res.estimates.samples} used; "
          f"float and fixed-point RLS, {len(res.parameters)} parameters)")
    # the writer, on the same frames: read + write, minus the read
    w_wall, w_cpu, same = best_of(lambda: rewrite(path, chunk_size), 1)
    r_wall, r_cpu, _ = best_of(read, 1)
    print(line("write_candump (read time subtracted)", frames, max(w_wall - r_wall, 1e-9),
               max(w_cpu - r_cpu, 1e-9)))
    print(f"  (the re-written log is {'byte for byte' if same else 'NOT'} the original)")
    return res.frames.total, wall, cpu


def rewrite(path: Path, chunk_size: int) -> bool:
    """Read the log and write it again with write_candump; True if the bytes are the same."""
    out = path.with_name(path.name + ".rewrite")
    try:
        write_candump(out, read_frames(path, chunk_size))
        return same_bytes(path, out)
    finally:
        out.unlink(missing_ok=True)


def same_bytes(a: Path, b: Path) -> bool:
    if a.stat().st_size != b.stat().st_size:
        return False
    with open(a, "rb") as fa, open(b, "rb") as fb:
        while True:
            x, y = fa.read(1 << 22), fb.read(1 << 22)
            if x != y:
                return False
            if not x:
                return True


# ------------------------------------------------------------------- the naive loop
def naive_loop(path: Path, max_frames: int, effects: str) -> tuple[int, int, list[float]]:
    """What a user would write: python-can reader, cantools decode, padasip RLS.

    Returns (frames read, samples fitted, weights).
    """
    import can
    import cantools
    import numpy as np
    import padasip

    from canrls.can.protocol import DEFAULT_DBC

    db = cantools.database.load_file(str(DEFAULT_DBC))
    cur_id = db.get_message_by_name("DriveCurrent").frame_id
    spd_id = db.get_message_by_name("DriveSpeed").frame_id
    orders = [int(e.split(":")[1]) for e in effects.split(",") if e.startswith("cogging:")]
    n = 4 + 2 + 2 * len(orders)  # J, B, Tc, T0, unbalance sin/cos, cogging sin/cos
    rls = padasip.filters.FilterRLS(n, mu=1.0, w="zeros")
    halves: dict[int, dict[str, Any]] = {}
    last: tuple[float, float] | None = None
    frames = samples = 0
    with can.LogReader(str(path)) as reader:
        for msg in reader:
            if frames >= max_frames:
                break
            frames += 1
            if msg.arbitration_id not in (cur_id, spd_id):
                continue
            sig = db.decode_message(msg.arbitration_id, msg.data)
            half = halves.setdefault(sig["Counter"], {})
            half.update(sig)
            half["t"] = msg.timestamp
            if "Current" not in half or "Speed" not in half:
                continue
            del halves[sig["Counter"]]
            w, theta, t = half["Speed"], half["Position"], half["t"]
            if last is not None and t > last[0]:
                acc = (w - last[1]) / (t - last[0])
                x = [acc, w, math.tanh(w / 0.01), 1.0, math.sin(theta), math.cos(theta)]
                for k in orders:
                    x += [math.sin(k * theta), math.cos(k * theta)]
                rls.adapt(KT * half["Current"], np.array(x))
                samples += 1
            last = (t, w)
    return frames, samples, list(rls.w)


def bench_naive(path: Path, max_frames: int, effects: str, total: int) -> tuple[float, float]:
    """Time the naive loop on the first frames; returns (wall, CPU) extrapolated to ``total``."""
    try:
        import padasip  # noqa: F401
    except ImportError:
        print("naive loop: padasip is not installed (pip install canrls[bench])")
        return math.nan, math.nan
    wall, cpu, (frames, samples, _) = best_of(
        lambda: naive_loop(path, max_frames, effects), 1)
    print(f"naive loop (can.LogReader -> cantools decode_message -> padasip FilterRLS.adapt), "
          f"run on the first {frames} frames ({samples} samples; timed after a warm-up run) "
          f"and extrapolated:")
    print(line(f"{frames} frames", frames, wall, cpu))
    scale = total / frames
    print(f"  extrapolated to {total} frames: {wall * scale:.0f} s "
          f"(CPU {cpu * scale:.0f} s)")
    return wall * scale, cpu * scale


# -------------------------------------------------------------------------- memory
def rss_child(path: Path, effects: str, chunk_size: int) -> None:
    """In a fresh process: RSS once set up, then peak RSS after prepare + fit_log."""
    # imports, protocol and the kernels run on a few frames: the baseline
    cfg = AppConfig()
    cfg.model = {"effects": effects.split(","), "kt": KT}
    protocol = cfg.protocol()
    proc = FrameProcessor(protocol, cfg.model_for(protocol), cfg.settings())
    for b in read_frames(path, 4096):
        proc.process(b)
        break
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    now = current_rss_kb()
    protocol, model, settings = configure(path, effects)
    res = fit_log(path, protocol, model, settings, chunk_size=chunk_size)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"frames": res.frames.total, "base_kb": base, "now_kb": now, "peak_kb": peak}))


def current_rss_kb() -> int | None:
    """Resident set size now [kB] (Linux ``/proc/self/status``), or None."""
    try:
        with open("/proc/self/status") as f:
            for text in f:
                if text.startswith("VmRSS:"):
                    return int(text.split()[1])
    except OSError:
        pass
    return None


def bench_memory(logs: list[tuple[str, Path]], effects: str, chunk_size: int) -> None:
    print("memory (peak RSS, resource.getrusage ru_maxrss, of a fresh process: imports, "
          "the kernels run once, then prepare + fit_log):")
    for label, path in logs:
        out = subprocess.run(
            [sys.executable, os.path.abspath(__file__), "--rss-child", str(path),
             "--effects", effects, "--chunk-size", str(chunk_size)],
            check=True, capture_output=True, text=True)
        d = json.loads(out.stdout.strip().splitlines()[-1])
        now = "" if d["now_kb"] is None else f"RSS {d['now_kb'] / 1024:.1f} MB, "
        print(f"  {label:>10} ({d['frames'] / 1e6:4.1f} M frames):  "
              f"peak RSS {d['peak_kb'] / 1024:6.1f} MB   (before the replay: {now}"
              f"peak {d['base_kb'] / 1024:.1f} MB)")


# ---------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=600.0,
                    help="seconds of drive in the log (default 600: 1.2 M frames)")
    ap.add_argument("--epoch", type=float, default=EPOCH,
                    help=f"time of the log's first frame [s] (default {EPOCH:g}, an epoch "
                         f"time as candump -l writes; 0: from zero)")
    ap.add_argument("--log", type=Path, default=None,
                    help="log to use (generated there if missing; default: cached under "
                         f"{tempfile.gettempdir()})")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--effects", default=EFFECTS, help=f"true and fitted effects ({EFFECTS})")
    ap.add_argument("--naive-frames", type=int, default=100_000,
                    help="frames given to the naive loop (default 100000)")
    ap.add_argument("--repeat", type=int, default=3, help="timed runs per figure (default 3)")
    ap.add_argument("--chunk-size", type=int, default=65536,
                    help="frames per block (fit_log's default 65536)")
    ap.add_argument("--no-memory", action="store_true", help="skip the peak-RSS runs")
    ap.add_argument("--rss-child", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.rss_child is not None:
        rss_child(args.rss_child, args.effects, args.chunk_size)
        return 0
    if not (args.duration > 0) or args.repeat < 1 or args.naive_frames < 1:
        ap.error("--duration, --repeat and --naive-frames must be positive")

    path = args.log or log_path(args.duration, args.seed, args.effects, args.epoch)
    ensure_log(path, args.duration, args.seed, args.effects, args.epoch)
    print(f"machine: {os.cpu_count()} CPUs, load average "
          f"{', '.join(f'{x:.2f}' for x in os.getloadavg())}")
    _, whole = bench_whole(path, args.effects, args.repeat)
    frames, wall, cpu = bench_canrls(path, args.effects, args.repeat, args.chunk_size)
    naive_wall, naive_cpu = bench_naive(path, min(args.naive_frames, frames), args.effects,
                                        frames)
    if math.isfinite(naive_wall):
        ratio = naive_wall / whole
        print(f"ratio canrls fit (whole process, median) / naive loop: {ratio:.0f} x on the "
              f"wall clock; goal >= {GOAL_RATIO:g} x: "
              f"{'met' if ratio >= GOAL_RATIO else 'NOT met'}")
        print(f"ratio fit_log (in one process) / naive loop: {naive_wall / wall:.0f} x on the "
              f"wall clock ({naive_cpu / cpu:.0f} x in CPU time)")
    if not args.no_memory:
        logs = []
        if args.log is None:
            short = args.duration / 6
            spath = log_path(short, args.seed, args.effects, args.epoch)
            ensure_log(spath, short, args.seed, args.effects, args.epoch)
            logs.append((f"{short / 60:g} min log", spath))
        logs.append((f"{args.duration / 60:g} min log" if args.log is None else path.name, path))
        bench_memory(logs, args.effects, args.chunk_size)
    return 0


if __name__ == "__main__":
    sys.exit(main())
