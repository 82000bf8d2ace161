"""Speed of one process serving every axis of a machine (``canrls run`` without ``--axis``).

Prints figures; it is not a test. For each number of axes N: a simulated machine of N
drives at 1 kHz (``canrls.sim.machine``, 2 feedback frames per axis and period, 2000 N
frames/s) is simulated and encoded first, then put on python-can's virtual channel at
its own rate by a feeder thread (as in ``tools/bench_daemon.py``) for ``--seconds``; the
N daemons of a :class:`~canrls.live.machine_daemon.MachineDaemon` (each its own virtual bus
connection, taking only its own feedback and command frames through the bus's filters
as ``canrls run`` of a machine sets them; ``--no-filter``: every frame) estimate and
publish.

* **lost**: frames an axis should have taken and had not 2 s after the feed ended
  (dropped, or still waiting), summed over the axes; 0 means the process kept up.
* **CPU per frame**: the daemons' listener and estimator thread CPU time, divided by the
  frames fed (with ``--no-filter`` every axis judges every frame: N times the work).
* **RSS** after the run, and the **cold start**: a fresh ``canrls run`` process of N
  axes from its start to its exit after ``--duration 0.01`` (imports, the machine
  checked, every daemon built, started and stopped).

Usage::

    python tools/bench_axes.py [--axes 1,2,4,8] [--seconds 5] [--no-filter]
"""

from __future__ import annotations

import argparse
import itertools
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_daemon import _feed  # the feeder of the one-drive benchmark, at a fixed rate
from canrls.live.daemon import Daemon
from canrls.live.daemon_settings import DaemonSettings
from canrls.live.machine_daemon import MachineDaemon
from canrls.processor.config import load_config
from canrls.sim.machine import AXIS_ID_STEP, machine, machine_frames

_ch = itertools.count()


def _rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _config(n: int, directory: Path) -> Path:
    """A configuration of ``n`` axes on the simulated machine's IDs."""
    p = directory / f"machine{n}.toml"
    p.write_text("[model]\nkt = 0.1\n" + "".join(
        f'[[axes]]\nname = "axis{k + 1}"\nids = "offset:{k * AXIS_ID_STEP:#x}"\n'
        for k in range(n)))
    return p


def bench(n: int, seconds: float, directory: Path, filtered: bool = True) -> dict[str, float]:
    """N axes fed ``seconds`` of the machine's frames at 1 kHz (``filtered``: each axis
    takes its own frames only, as ``canrls run`` does)."""
    msgs = [m for b in machine_frames(machine(n, duration=seconds, seed=1))
            for m in b.to_messages()]
    rate = 2000.0 * n
    ch = f"bench-axes-{next(_ch)}"
    daemons = {}
    for name, cfg in load_config(_config(n, directory)).axis_configs().items():
        protocol = cfg.protocol()
        dset = DaemonSettings(queue_size=max(1000, int(rate * 0.5)),
                              own_offset=DaemonSettings.from_config(cfg).own_offset,
                              rx_filter=filtered)
        daemons[name] = Daemon(protocol, cfg.model_for(protocol), cfg.settings(), dset,
                               bus={"interface": "virtual", "channel": ch})
    md = MachineDaemon(daemons)
    md.start()
    try:
        time.sleep(0.3)
        cpu0 = sum(d.stats().estimator_cpu_s + d.stats().listener_cpu_s
                   for d in daemons.values())
        took = _feed(ch, msgs, rate)
        want_n = len(msgs) // n if filtered else len(msgs)
        md.wait_for(lambda x: all(d.stats().frames >= want_n and d.stats().backlog == 0
                                  for d in x.daemons.values()), 2.0)
        stats = [d.stats() for d in daemons.values()]
    finally:
        md.stop()
    cpu = sum(s.estimator_cpu_s + s.listener_cpu_s for s in stats) - cpu0
    # every frame an axis should have taken (its own, or all without the filters) and
    # did not within 2 s of the end, dropped or still waiting, is lost
    want = len(msgs) // n if filtered else len(msgs)
    lost = sum(max(s.rx_overflow + s.counters["frames_lost"], want - s.frames)
               for s in stats)
    return {"axes": n, "offered": len(msgs) / took, "lost": lost,
            "cpu_us": cpu / len(msgs) * 1e6, "rss_mb": _rss_mb()}


def cold_start(n: int, directory: Path) -> float:
    """Seconds of a fresh ``canrls run`` of ``n`` axes, start to exit."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "canrls", "run", "--config",
                    str(_config(n, directory)), "-i", "virtual", "-c", f"cold-{n}",
                    "--duration", "0.01"], check=True, capture_output=True, timeout=120)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--axes", default="1,2,4,8", help="numbers of axes, comma-separated")
    ap.add_argument("--seconds", type=float, default=5.0, help="seconds of traffic each")
    ap.add_argument("--no-filter", action="store_true",
                    help="every axis takes every frame of the bus (no filters)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        print(f"{'axes':>4}  {'frames/s':>9}  {'lost':>7}  {'CPU µs/frame':>12}  "
              f"{'RSS MB':>7}  {'cold start s':>12}")
        for n in (int(x) for x in args.axes.split(",")):
            r = bench(n, args.seconds, Path(tmp), filtered=not args.no_filter)
            c = cold_start(n, Path(tmp))
            print(f"{n:>4}  {r['offered']:>9.0f}  {r['lost']:>7.0f}  {r['cpu_us']:>12.1f}  "
                  f"{r['rss_mb']:>7.0f}  {c:>12.2f}", flush=True)


if __name__ == "__main__":
    main()
