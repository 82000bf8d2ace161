"""Speed of one process serving every axis of a machine (``canrls run`` without ``--axis``).

Prints figures; it is not a test. For each number of axes N: a simulated machine of N
drives at 1 kHz (``canrls.sim.machine``, 2 feedback frames per axis and period, 2000 N
frames/s) is simulated and encoded first (at most :data:`SEGMENT_S`; a longer run feeds
that stretch again, later each time), then put on python-can's virtual channel at its
own rate by a feeder thread (as in ``tools/bench_daemon.py``) for ``--seconds``; the N
daemons of a :class:`~canrls.live.machine_daemon.MachineDaemon` (one bus connection and
reader for all, each axis taking its own feedback and command frames, as ``canrls run``
of a machine; ``--no-filter``: each axis a connection of its own, taking every frame)
estimate and publish. Each axis is built as ``canrls run`` builds it
(:func:`canrls.cli.run.daemon_for`): its fixed column the target's integer path by
default, ``--fixed kernel`` the kernel's on the float front end.

* **lost**: frames an axis should have taken and had not 2 s after the feed ended
  (dropped, or still waiting), summed over the axes; 0 means the process kept up.
* **CPU per frame**: the thread CPU time of the machine's bus reader (one for every
  axis, :class:`~canrls.live.hub.BusHub`) and the axes' estimator threads, divided by the
  frames fed (with ``--no-filter`` every axis has a bus of its own and judges every
  frame: N times the work). The feeder's time is not the daemon's.
* **publication period** of the axes other than the first: the largest gap between two
  publications of one axis (their parameter frames sent), and the 99th percentile, in
  ms (``publish_interval`` 100 ms). With ``--flood RATE`` the first axis also gets RATE
  frames/s of seeded garbage on its current feedback ID, spread over the run: the
  others' frames, estimates and publication period must not notice (issue 31, a fault
  on one axis never changes another axis's timing).
* **RSS** after the run (this process: the simulated frames and the feeder included),
  and the **cold start**: a fresh ``canrls run`` process of N axes from its start to its
  exit after ``--duration 0.01`` (imports, the machine checked, every daemon built,
  started and stopped) with canrls's bytecode cached as an installed package has it,
  that process's peak RSS, and the start without bytecode (``PYTHONDONTWRITEBYTECODE``:
  every module of canrls compiled at each start).

Usage::

    python tools/bench_axes.py [--axes 1,2,4,8] [--seconds 5] [--no-filter] [--flood 0]
                               [--fixed target]
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import numpy as np
from can.interfaces import virtual as _virtual

from canrls.can.frameblock import FrameBlock
from canrls.cli.run import daemon_for
from canrls.live.daemon_settings import FIXED_PATHS, DaemonSettings
from canrls.live.machine_daemon import MachineDaemon
from canrls.processor.config import load_config
from canrls.sim.machine import AXIS_ID_STEP, machine, machine_frames

_ch = itertools.count()
#: the longest simulated stretch [s]; a longer run feeds it again, later each time
SEGMENT_S = 10.0
#: ``python -m canrls ARGS`` that prints its peak RSS (``VmHWM``) to stderr at exit (a
#: child's ``ru_maxrss`` would count the parent's pages at the fork)
_PEAK = ("import atexit, runpy, sys; atexit.register(lambda: print(next(ln for ln in "
         "open('/proc/self/status') if ln.startswith('VmHWM:')), end='', file=sys.stderr)); "
         "sys.argv = ['canrls', *sys.argv[1:]]; runpy.run_module('canrls', run_name='__main__')")


def _rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _config(n: int, directory: Path, fixed: str) -> Path:
    """A configuration of ``n`` axes on the simulated machine's IDs, ``[daemon] fixed``
    the published fixed column."""
    p = directory / f"machine{n}.toml"
    p.write_text(f'[model]\nkt = 0.1\n[daemon]\nfixed = "{fixed}"\n' + "".join(
        f'[[axes]]\nname = "axis{k + 1}"\nids = "offset:{k * AXIS_ID_STEP:#x}"\n'
        for k in range(n)))
    return p


def _flooded(block: FrameBlock, frame_id: int, rate: float, seconds: float) -> FrameBlock:
    """``block`` with ``rate`` frames/s of seeded garbage on ``frame_id`` spread among its
    frames (in time order)."""
    rng = np.random.default_rng(31)
    k = int(rate * seconds)
    flood = FrameBlock.allocate(k)
    flood.t[:] = seconds * (np.arange(k) + 0.5) / k
    flood.arbitration_id[:] = frame_id
    flood.dlc[:] = 8
    flood.data[:] = rng.integers(0, 256, (k, 8), np.uint8)
    both = FrameBlock.concat([block, flood])
    return both.take(np.argsort(both.t, kind="stable"))


def _chunks(segment: FrameBlock, seconds: float, repeats: int) -> Iterator[list[can.Message]]:
    """The segment's frames ``repeats`` times, each time ``seconds`` later, as messages
    made 20 ms of the machine at a time (a long run never holds them all, and the feeder
    never holds the interpreter long)."""
    edges = np.searchsorted(segment.t, np.arange(0.0, seconds + 0.04, 0.02))
    for k in range(repeats):
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            part = segment.take(slice(lo, hi))
            msgs = part.to_messages()
            for m in msgs:
                m.timestamp += k * seconds
            yield msgs


def _feed(ch: str, chunks: Iterator[list[can.Message]], total: int, rate: float,
          tick: float = 1e-3) -> float:
    """Put ``total`` frames of ``chunks`` on the channel at ``rate`` frames/s, the frames
    due every ``tick`` (as ``tools/bench_daemon.py`` does); returns the duration."""
    with _virtual.channels_lock:
        queues = list(_virtual.channels[ch])
    buf: list[can.Message] = []
    t0 = time.perf_counter()
    k = step = 0
    while k < total:
        step += 1
        due = min(total, int((time.perf_counter() - t0) * rate) + 1)
        while k < due:
            while not buf:
                buf = next(chunks)[::-1]
            m = buf.pop()
            for q in queues:
                q.put_nowait(m)
            k += 1
        wait = t0 + step * tick - time.perf_counter()
        if wait > 0:
            time.sleep(wait)
    return time.perf_counter() - t0


def _gaps(times: list[float]) -> tuple[float, float]:
    """The largest gap between publications and its 99th percentile [ms]."""
    d = np.diff(times) * 1e3
    return (float(d.max()), float(np.percentile(d, 99))) if len(d) else (np.nan, np.nan)


def bench(n: int, seconds: float, directory: Path, filtered: bool = True,
          flood: float = 0.0, fixed: str = DaemonSettings().fixed) -> dict[str, float]:
    """N axes fed ``seconds`` of the machine's frames at 1 kHz (``filtered``: each axis
    takes its own frames only, as ``canrls run`` does; ``flood``: frames/s of garbage on
    the first axis's feedback ID; ``fixed``: ``[daemon] fixed``, the published column)."""
    # a run longer than SEGMENT_S: the machine's first SEGMENT_S again and again, later
    # each time (the alive counters go round whole: 10,000 periods of 16)
    segment_s = min(seconds, SEGMENT_S)
    repeats = math.ceil(seconds / segment_s)
    segment = FrameBlock.concat(machine_frames(machine(n, duration=segment_s, seed=1)))
    own = len(segment) * repeats
    ch = f"bench-axes-{next(_ch)}"
    daemons = {}
    sent: dict[str, list[float]] = {}

    def on_publish(name: str) -> Callable[[int, float], None]:
        return lambda frames, at: sent[name].append(at)

    for name, cfg in load_config(_config(n, directory, fixed)).axis_configs().items():
        protocol = cfg.protocol()
        if flood and not daemons:
            segment = _flooded(segment, protocol.messages[0].frame_id, flood, segment_s)
        dset = DaemonSettings(queue_size=max(1000, int(2000.0 * n * 0.5)),
                              own_offset=DaemonSettings.from_config(cfg).own_offset,
                              rx_filter=filtered, fixed=fixed)
        sent[name] = []
        daemons[name] = daemon_for(protocol, cfg.model_for(protocol), cfg.settings(), dset,
                                   bus={"interface": "virtual", "channel": ch},
                                   on_publish=on_publish(name))
    total = len(segment) * repeats
    rate = len(segment) / segment_s
    md = MachineDaemon(daemons)
    md.start()
    try:
        time.sleep(0.3)
        rx0 = md.reader_cpu_s + sum(d.stats().listener_cpu_s for d in daemons.values())
        est0 = sum(d.stats().estimator_cpu_s for d in daemons.values())
        for times in sent.values():
            times.clear()
        took = _feed(ch, _chunks(segment, segment_s, repeats), total, rate)
        want_n = own // n if filtered else total
        md.wait_for(lambda x: all(d.stats().frames >= want_n and d.stats().backlog == 0
                                  for d in x.daemons.values()), 2.0)
        stats = [d.stats() for d in daemons.values()]
        rx = md.reader_cpu_s + sum(s.listener_cpu_s for s in stats) - rx0
    finally:
        md.stop()
    est = sum(s.estimator_cpu_s for s in stats) - est0
    # every frame an axis should have taken (its own, or all without the filters) and
    # did not within 2 s of the end, dropped or still waiting, is lost
    want = own // n if filtered else total
    others = stats[1:] if flood else stats  # the flooded axis drops its flood: its own
    lost = sum(max(s.rx_overflow + s.counters["frames_lost"], want - s.frames)
               for s in others)
    gaps = [_gaps(t) for t in list(sent.values())[1:]] or [(np.nan, np.nan)]
    return {"axes": n, "offered": total / took, "lost": lost,
            "cpu_us": (rx + est) / total * 1e6, "rx_us": rx / total * 1e6,
            "est_us": est / total * 1e6, "rss_mb": _rss_mb(),
            "gap_max": max(g[0] for g in gaps), "gap_p99": max(g[1] for g in gaps)}


def cold_start(n: int, directory: Path, fixed: str,
               compiled: bool = True) -> tuple[float, float]:
    """Seconds of a fresh ``canrls run`` of ``n`` axes, start to exit, and its peak RSS
    [MB]. ``compiled``: with Python's bytecode of canrls written and read (as an
    installed package has it; one run first writes it even where
    ``PYTHONDONTWRITEBYTECODE`` is set); else as the environment says."""
    env = dict(os.environ)
    if compiled:
        env.pop("PYTHONDONTWRITEBYTECODE", None)
    argv = [sys.executable, "-c", _PEAK, "run", "--config", str(_config(n, directory, fixed)),
            "-i", "virtual", "-c", f"cold-{n}", "--duration", "0.01"]
    for _ in range(2 if compiled else 1):
        t0 = time.perf_counter()
        r = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=120)
        took = time.perf_counter() - t0
        if r.returncode != 0:
            raise SystemExit(f"error: canrls run of {n} axes exited {r.returncode}: "
                             f"{r.stderr.strip()}")
    peak = [ln for ln in r.stderr.splitlines() if ln.startswith("VmHWM:")]
    return took, int(peak[-1].split()[1]) / 1024.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--axes", default="1,2,4,8", help="numbers of axes, comma-separated")
    ap.add_argument("--seconds", type=float, default=5.0, help="seconds of traffic each")
    ap.add_argument("--no-filter", action="store_true",
                    help="every axis takes every frame of the bus (no filters)")
    ap.add_argument("--flood", type=float, default=0.0,
                    help="frames/s of garbage on the first axis's feedback ID (default 0)")
    ap.add_argument("--fixed", choices=FIXED_PATHS, default=DaemonSettings().fixed,
                    help="[daemon] fixed of every axis: the published fixed column (default: "
                         "the daemon's default, the target's integer path; 'kernel' for "
                         "comparison)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        print(f"{'axes':>4}  {'frames/s':>9}  {'lost':>7}  {'CPU µs/frame':>12}  "
              f"{'(reader':>7}  {'estim.)':>7}  {'gap max ms':>10}  {'p99':>6}  "
              f"{'RSS MB':>7}  {'cold start s':>12}  {'(RSS MB)':>8}  {'no .pyc s':>9}")
        for n in (int(x) for x in args.axes.split(",")):
            r = bench(n, args.seconds, Path(tmp), filtered=not args.no_filter,
                      flood=args.flood, fixed=args.fixed)
            c, c_rss = cold_start(n, Path(tmp), args.fixed)
            c_src = cold_start(n, Path(tmp), args.fixed, compiled=False)[0]
            print(f"{n:>4}  {r['offered']:>9.0f}  {r['lost']:>7.0f}  {r['cpu_us']:>12.1f}  "
                  f"{r['rx_us']:>7.1f}  {r['est_us']:>7.1f}  {r['gap_max']:>10.1f}  "
                  f"{r['gap_p99']:>6.1f}  {r['rss_mb']:>7.0f}  {c:>12.2f}  {c_rss:>8.0f}  "
                  f"{c_src:>9.2f}", flush=True)


if __name__ == "__main__":
    main()
