"""Speed of the daemon on python-can's virtual bus, the simulated drive in the same process.

Prints figures; it is not a test. The drive's frames are simulated and encoded before
the timed part (or in the feeder thread for the memory run) and put on the virtual
channel by a feeder thread at a fixed rate, so the simulator's CPU is not the daemon's.
The daemon is the one ``canrls run`` builds (:func:`canrls.cli.run.daemon_for`): its
published fixed column the target's integer path, as ``[daemon] fixed`` has it by
default; ``--fixed kernel`` measures the kernel's column on the float front end instead.

* **throughput**: for each offered rate (frames/s), ``--seconds`` of traffic; a rate
  is sustained when no frame is lost (the daemon's queue holds at most half a second
  of frames, overflow counts as loss) and the backlog drains within a second.
* **CPU per frame**: thread CPU time (``time.thread_time``) of the daemon's bus
  listener (python-can's notifier thread) and estimator thread, divided by frames.
* **latency**: at ``--latency-rate`` frames/s with ``publish_interval = 0`` and
  ``block_interval = 0`` (publish after every block): from the moment a feedback frame
  is put on the bus to the moment the parameter frames that include it are sent;
  p50 and p99 of each of ``--latency-runs`` runs.
* **memory**: resident set size while ``--memory-sim-s`` seconds of simulated traffic
  (default one hour) go through as fast as the daemon takes them; first, the floor of
  a fresh process that only imports the daemon and builds one (no simulator, no
  frame), step by step (numpy + python-can + cantools, canrls's daemon modules, one
  daemon). The memory over simulated traffic includes the simulated drive in the same
  process: the daemon's own figure over a bus is ``tools/bench_live.py``'s.

Usage::

    python tools/bench_daemon.py [--rates 9000,18000,27000,54000,90000] [--seconds 5] [--tick 0.001]
                                 [--latency-rate 9000] [--latency-runs 3]
                                 [--memory-sim-s 3600] [--skip-memory] [--fixed target]
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import subprocess
import sys
import time
from collections.abc import Callable

import can
import numpy as np
from can.interfaces import virtual as _virtual

from canrls.cli.run import daemon_for
from canrls.live.daemon import Daemon
from canrls.live.daemon_settings import FIXED_PATHS, DaemonSettings
from canrls.processor.config import AppConfig
from canrls.sim.scenario import Simulator, scenario

#: n = 8: inertia, viscous, coulomb, offset, unbalance (2), cogging:6 (2)
EFFECTS = "inertia,viscous,coulomb,offset,unbalance,cogging:6"
_ch = itertools.count()


def _rss_mb(field: str = "VmRSS") -> float:
    """``VmRSS`` of this process [MB], or another field of /proc/self/status
    (``RssAnon``: private memory; ``RssFile``: pages of mapped files such as the shared
    libraries, which the kernel can drop and read again)."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _messages(seconds: float, seed: int = 1) -> list[can.Message]:
    sc = scenario("standard", effects=EFFECTS, seed=seed, duration=seconds, excitation="slow")
    out: list[can.Message] = []
    for b in Simulator(sc, t0=0.0).frames(20000):
        out += b.to_messages()
    return out


def _daemon(channel: str, settings: DaemonSettings, fixed: str,
            on_publish: Callable[[int, float], None] | None = None) -> Daemon:
    """The daemon ``canrls run`` builds of these ``settings``, its fixed column ``fixed``
    (``[daemon] fixed``: the target's integer path or the kernel's)."""
    cfg = AppConfig()
    cfg.model = {"effects": EFFECTS.split(","), "kt": 0.1}
    protocol = cfg.protocol()
    model = cfg.model_for(protocol)
    assert len(model.parameters) == 8
    return daemon_for(protocol, model, cfg.settings(),
                      dataclasses.replace(settings, fixed=fixed),
                      bus={"interface": "virtual", "channel": channel}, on_publish=on_publish)


def _feed(channel: str, msgs: list[can.Message], rate: float,
          sent_at: np.ndarray | None = None, tick: float = 1e-3) -> float:
    """Put ``msgs`` on the channel at ``rate`` frames/s; returns the duration.

    Every ``tick`` seconds (as closely as ``time.sleep`` allows) the frames due by then
    go out: 1 ms is how a USB adapter delivers them; a shorter tick spreads them out
    as on a bus seen through SocketCAN, and makes the bus reader wake once per frame.
    """
    with _virtual.channels_lock:
        queues = list(_virtual.channels[channel])
    t0 = time.perf_counter()
    k = 0
    n = len(msgs)
    step = 0
    while k < n:
        step += 1
        now = time.perf_counter()
        target = min(n, int((now - t0) * rate) + 1)
        for i in range(k, target):
            if sent_at is not None:
                sent_at[i] = now
            for q in queues:
                q.put_nowait(msgs[i])
        k = max(k, target)
        wait = t0 + step * tick - time.perf_counter()
        if wait > 0:
            time.sleep(wait)
    return time.perf_counter() - t0


def bench_rate(msgs: list[can.Message], rate: float, fixed: str, tick: float = 1e-3,
               block_interval: float | None = None) -> dict[str, float]:
    ch = f"bench-{next(_ch)}"
    settings = DaemonSettings(queue_size=max(1000, int(rate * 0.5)))
    if block_interval is not None:
        settings = dataclasses.replace(settings, block_interval=block_interval)
    d = _daemon(ch, settings, fixed)
    d.start()
    try:
        time.sleep(0.3)
        est0, rx0 = d.stats().estimator_cpu_s, d.stats().listener_cpu_s
        took = _feed(ch, msgs, rate, tick=tick)
        drained = d.wait_for(lambda x: x.stats().frames >= len(msgs) - x.stats().rx_overflow
                             and x.stats().backlog == 0, 1.0)
        s = d.stats()
    finally:
        d.stop()
    lost = s.rx_overflow + s.counters["frames_lost"]
    return {"offered": len(msgs) / took, "frames": s.frames, "lost": lost,
            "drained": float(drained),
            "cpu_us": (s.estimator_cpu_s - est0 + s.listener_cpu_s - rx0) / max(s.frames, 1) * 1e6,
            "est_us": (s.estimator_cpu_s - est0) / max(s.frames, 1) * 1e6,
            "rx_us": (s.listener_cpu_s - rx0) / max(s.frames, 1) * 1e6,
            "blocks": s.blocks}


def bench_latency(msgs: list[can.Message], rate: float, fixed: str,
                  tick: float = 1e-3) -> tuple[float, float, int]:
    ch = f"bench-lat-{next(_ch)}"
    sent_at = np.full(len(msgs), np.nan)
    pubs: list[tuple[int, float]] = []
    d = _daemon(ch, DaemonSettings(publish_interval=0.0, block_interval=0.0), fixed,
                on_publish=lambda n, t: pubs.append((n, t)))
    d.start()
    try:
        time.sleep(0.3)
        base = d.stats().frames
        _feed(ch, msgs, rate, sent_at, tick)
        d.wait_for(lambda x: x.stats().frames >= base + len(msgs), 2.0)
    finally:
        d.stop()
    lat = np.full(len(msgs), np.nan)
    prev = 0
    for n, t in pubs:
        n -= base
        if n > prev:
            lat[prev:n] = t - sent_at[prev:n]
            prev = n
    lat = lat[np.isfinite(lat)] * 1e3
    return float(np.percentile(lat, 50)), float(np.percentile(lat, 99)), len(lat)


_FLOOR = """
import numpy, can, cantools
def rss(field="VmRSS"):
    return int([l for l in open("/proc/self/status") if l.startswith(field)][0].split()[1])
a = rss()
from canrls.processor.config import AppConfig
from canrls.live.daemon import DaemonSettings
from canrls.cli.run import daemon_for
c = rss()
cfg = AppConfig()
cfg.model = {"effects": %r, "kt": 0.1}
protocol = cfg.protocol()
daemon_for(protocol, cfg.model_for(protocol), cfg.settings(), DaemonSettings(fixed=%r),
           bus={"interface": "virtual", "channel": "floor"})
print(a, c, rss(), rss("RssAnon"), rss("RssFile"))
"""


def memory_floor(fixed: str) -> tuple[float, ...]:
    """RSS [MB] of a fresh process: numpy + python-can + cantools imported, then
    canrls' daemon modules, then one daemon built (then also split into private and
    file-backed pages); no simulator and no frame yet."""
    out = subprocess.run([sys.executable, "-c", _FLOOR % (EFFECTS.split(","), fixed)],
                         capture_output=True, text=True, check=True).stdout.split()
    return tuple(int(x) / 1024.0 for x in out)


def bench_memory(sim_seconds: float, report_every: float, fixed: str
                 ) -> list[tuple[float, float, float]]:
    ch = f"bench-mem-{next(_ch)}"
    d = _daemon(ch, DaemonSettings(queue_size=200000), fixed)
    sc = scenario("standard", effects=EFFECTS, seed=2, duration=sim_seconds,
                  excitation="standard")
    sim = Simulator(sc, t0=0.0)
    rows: list[tuple[float, float, float]] = []
    d.start()
    try:
        with _virtual.channels_lock:
            queues = list(_virtual.channels[ch])
        next_report = 0.0
        for block in sim.frames(10000):
            for m in block.to_messages():
                for q in queues:
                    q.put_nowait(m)
            while d.stats().backlog > 20000:  # as fast as the daemon takes them
                time.sleep(0.01)
            t = float(block.t[-1])
            if t >= next_report:
                rows.append((t, _rss_mb(), _rss_mb("RssAnon")))
                next_report += report_every
        d.wait_for(lambda x: x.stats().backlog == 0, 30)
        rows.append((sim_seconds, _rss_mb(), _rss_mb("RssAnon")))
    finally:
        d.stop()
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rates", default="9000,18000,27000,54000,90000")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--latency-rate", type=float, default=9000.0)
    ap.add_argument("--latency-runs", type=int, default=3,
                    help="latency runs, each with other frames (the host's speed varies)")
    ap.add_argument("--memory-sim-s", type=float, default=3600.0)
    ap.add_argument("--skip-memory", action="store_true")
    ap.add_argument("--block-interval", type=float, default=None,
                    help="[daemon] block_interval of the throughput runs (default: its default)")
    ap.add_argument("--tick", type=float, default=1e-3,
                    help="seconds between the feeder's hand-overs (default 1 ms, as USB)")
    ap.add_argument("--fixed", choices=FIXED_PATHS, default=DaemonSettings().fixed,
                    help="[daemon] fixed: the published fixed column (default: the daemon's "
                         "default, the target's integer path; 'kernel' for comparison)")
    args = ap.parse_args()
    rates = [float(r) for r in args.rates.split(",")]
    print(f"daemon on the virtual bus, n = 8 ({EFFECTS}), float + fixed RLS, the fixed "
          f"column the {args.fixed}'s; frames handed over every {args.tick * 1e3:g} ms")
    print(f"RSS at start {_rss_mb():.0f} MB")
    for rate in rates:
        msgs = _messages(args.seconds * rate / 2000.0)
        r = bench_rate(msgs, rate, args.fixed, args.tick, args.block_interval)
        ok = "sustained" if r["lost"] == 0 and r["drained"] else "NOT sustained"
        print(f"offered {r['offered']:8.0f} frames/s: {ok:13s} lost {r['lost']:.0f}, "
              f"daemon CPU {r['cpu_us']:.1f} us/frame (listener {r['rx_us']:.1f}, "
              f"estimator {r['est_us']:.1f}), {r['frames'] / max(r['blocks'], 1):.0f} frames/block")
    runs = []
    for k in range(args.latency_runs):
        msgs = _messages(args.seconds * args.latency_rate / 2000.0, seed=3 + k)
        runs.append(bench_latency(msgs, args.latency_rate, args.fixed, args.tick))
    print(f"latency feedback frame -> parameter frame at {args.latency_rate:.0f} frames/s "
          f"(publish after every block), p50 / p99 of each run: "
          + ", ".join(f"{p50:.2f} / {p99:.2f} ms" for p50, p99, _ in runs)
          + f" ({runs[0][2]} frames a run)")
    if not args.skip_memory:
        a, c, d, anon, file = memory_floor(args.fixed)
        print(f"memory floor of the daemon alone (fresh process, before any frame): "
              f"numpy + python-can + cantools {a:.0f} MB, "
              f"+ canrls {c:.0f} MB, one daemon built {d:.0f} MB "
              f"({anon:.0f} MB private, {file:.0f} MB of mapped files)")
        t0 = time.perf_counter()
        rows = bench_memory(args.memory_sim_s, args.memory_sim_s / 6, args.fixed)
        wall = time.perf_counter() - t0
        print(f"memory over {args.memory_sim_s:g} s of simulated traffic ({wall:.0f} s wall; "
              f"the simulated drive runs in the same process), "
              f"RSS (of which private): "
              + ", ".join(f"{t:.0f} s: {m:.0f} ({a:.0f}) MB" for t, m, a in rows))


if __name__ == "__main__":
    main()
