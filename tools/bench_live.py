#!/usr/bin/env python3
"""The live figures of issue 14 (item 6), each printed against its goal, with real processes.

Prints figures; it is not a test. Four processes share one bus, bound to 127.0.0.1:

1. a python-can-remote server (``python -m can_remote``, a virtual bus behind it);
2. a sender (this script with ``--send``, a python-can client of the server) putting
   the simulated drive's feedback frames on the bus at a fixed rate (two frames per
   control period; the frames are simulated before the clock starts);
3. ``canrls run -i remote`` (the daemon, n = 8 parameters, float and fixed point);
4. this script, a client that only keeps the parameter frames the daemon publishes.

Two runs:

* **1 kHz** (2,000 frames/s) for ``--duration`` seconds (default 60). The sender runs
  before the daemon starts (a drive on the bus), and the daemon starts cold: a fresh
  process with an empty ``$HOME`` and cache directory (no compiled kernels). Figures:
  the time from the daemon's start to the first parameter frame on the bus (goal 3 s);
  its resident memory after ``--duration`` seconds (or 5 s after the first parameter
  frame, if that came later; ``VmRSS``, goal 100 MB; the peak
  ``VmHWM`` beside it); its CPU per frame in the steady state, the whole process from
  /proc (python-can-remote's websocket client included; goal 20 us), and beside it the
  daemon's estimator thread and bus listener thread (the notifier, which runs the
  websocket client) over the whole run, from ``canrls run --json``.
* **18,000 frames/s** (twice a saturated 1 Mbit/s bus) for ``--fast-seconds``
  (default 10): frames the sender sent against frames the daemon processed (goal: none
  lost), the daemon's queue overflow, and its CPU per frame at that rate. The frames
  carry the server's arrival times, so the alive-counter check may infer losses from
  the websocket's stalls; that count is printed beside, for information.

Usage::

    python tools/bench_live.py [--duration 60] [--fast-seconds 10] [--fast-rate 18000]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import can

from bench_daemon import EFFECTS, _messages
from canrls.can.frames import frame_ids
from live_vs_offline import free_port, wait_port

PY = sys.executable
#: goals of issue 14, item 6
GOAL_RSS_MB, GOAL_START_S, GOAL_CPU_US, GOAL_RATE = 100.0, 3.0, 20.0, 18000.0
CLK_TCK = os.sysconf("SC_CLK_TCK")


def send(url: str, rate: float, seconds: float, seed: int) -> None:
    """The sender: ``seconds`` of frames at ``rate`` frames/s; prints what it sent (JSON)."""
    msgs = _messages(seconds * rate / 2000.0 + 0.01, seed)[:int(seconds * rate)]
    bus = can.Bus(interface="remote", channel=url)
    try:
        print(json.dumps({"ready": True}), flush=True)
        sys.stdin.readline()  # go
        t0 = time.perf_counter()
        k, step, n = 0, 0, len(msgs)
        while k < n:  # every millisecond, the frames due by then
            step += 1
            target = min(n, int((time.perf_counter() - t0) * rate) + 1)
            for i in range(k, target):
                bus.send(msgs[i])
            k = max(k, target)
            wait = t0 + step * 1e-3 - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
        took = time.perf_counter() - t0
    finally:
        bus.shutdown()
    print(json.dumps({"sent": n, "seconds": took}), flush=True)


def _proc(p: subprocess.Popen[str]) -> tuple[float, float, float]:
    """(VmRSS, VmHWM) [MB] and CPU time [s] (user + system) of the running process ``p``."""
    if p.poll() is not None:
        _, err = p.communicate()
        sys.stderr.write(err)
        raise SystemExit(f"error: {' '.join(map(str, p.args))} exited {p.returncode}")
    pid = p.pid
    mem = {}
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                mem[key] = int(value.split()[0]) / 1024.0
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return mem["VmRSS"], mem["VmHWM"], (int(fields[11]) + int(fields[12])) / CLK_TCK


class Watcher(can.Listener):
    """This script's client: the arrival time of the first parameter frame."""

    def __init__(self) -> None:
        self.first: float | None = None
        self.count = 0
        self.seen = threading.Event()

    def on_message_received(self, msg: can.Message) -> None:
        self.count += 1
        if self.first is None:
            self.first = time.time()
            self.seen.set()


class Setup:
    """The server, the sender, the daemon and this script's client, stopped on exit."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.port = free_port()
        self.url = f"ws://127.0.0.1:{self.port}/"
        self.procs: list[subprocess.Popen[str]] = []
        self.client: can.BusABC | None = None
        self.notifier: can.Notifier | None = None

    def __enter__(self) -> Setup:
        self.procs.append(subprocess.Popen(
            [PY, "-m", "can_remote", "-i", "virtual", "-c", f"bench-live-{self.port}",
             "-H", "127.0.0.1", "-p", str(self.port)],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, text=True))
        wait_port(self.port, 20)
        return self

    def watch(self) -> Watcher:
        ids = frame_ids()
        w = Watcher()
        self.client = can.Bus(interface="remote", channel=self.url, can_filters=[
            {"can_id": i, "can_mask": 0x7FF, "extended": False} for i in ids.published])
        self.notifier = can.Notifier(self.client, [w], timeout=0.1)
        return w

    def sender(self, rate: float, seconds: float, seed: int) -> subprocess.Popen[str]:
        p = subprocess.Popen([PY, __file__, "--send", self.url, "--rate", str(rate),
                              "--seconds", str(seconds), "--seed", str(seed)],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.procs.append(p)
        assert p.stdout is not None
        json.loads(p.stdout.readline())  # ready: frames simulated, connected
        return p

    def daemon(self, duration: float, cold: bool, period: float | None = None
               ) -> subprocess.Popen[str]:
        """``canrls run``; ``period``: the control period the sender's rate makes (the
        DBC's 1 ms holds only at 2,000 frames/s, and the daemon checks it)."""
        env = dict(os.environ)
        if cold:  # a fresh home: no cache of compiled kernels anywhere
            home = self.tmp / f"home-{len(self.procs)}"
            home.mkdir()
            env.pop("NUMBA_CACHE_DIR", None)
            env.update(HOME=str(home), XDG_CACHE_HOME=str(home / ".cache"))
        p = subprocess.Popen([PY, "-m", "canrls", "run", "-i", "remote", "-c", self.url,
                              "--effects", EFFECTS, "--kt", "0.1", "--duration", f"{duration:g}",
                              "--json", *(["--period", repr(period)] if period else [])],
                             env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
        self.procs.append(p)
        return p

    def __exit__(self, *exc: object) -> None:
        if self.notifier is not None:
            self.notifier.stop()
        if self.client is not None:
            self.client.shutdown()
        for p in reversed(self.procs):
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()


def _go(p: subprocess.Popen[str]) -> None:
    assert p.stdin is not None
    p.stdin.write("go\n")
    p.stdin.flush()


def _finish(p: subprocess.Popen[str], timeout: float) -> dict[str, Any]:
    out, err = p.communicate(timeout=timeout)
    if p.returncode != 0:
        sys.stderr.write(err)
        raise SystemExit(f"error: {' '.join(map(str, p.args))} exited {p.returncode}")
    return json.loads(out.strip().splitlines()[-1] if p.args[1] == __file__ else out)


def run_1khz(duration: float) -> dict[str, float]:
    rate = 2000.0
    with tempfile.TemporaryDirectory() as tmp, Setup(Path(tmp)) as s:
        watcher = s.watch()
        sender = s.sender(rate, duration + 30.0, seed=1)
        _go(sender)
        time.sleep(1.0)
        t0 = time.time()
        d = s.daemon(duration + 600.0, cold=True)
        if not watcher.seen.wait(300.0):
            raise SystemExit("error: no parameter frame from the daemon within 300 s")
        first = (watcher.first or t0) - t0
        time.sleep(max(0.0, first + 3.0 - (time.time() - t0)))  # past the start
        _, _, cpu1 = _proc(d)
        c1 = time.perf_counter()
        # `duration` seconds running (from its first parameter frame if it came later)
        time.sleep(max(0.0, t0 + max(duration, first + 5.0) - time.time()))
        rss, hwm, cpu2 = _proc(d)
        c2 = time.perf_counter()
        d.terminate()
        live = _finish(d, 60)["daemon"]
    frames = live["frames"]
    return {"first_s": first, "rss_mb": rss, "hwm_mb": hwm,
            "cpu_us": (cpu2 - cpu1) / (rate * (c2 - c1)) * 1e6,
            "est_us": live["estimator_cpu_s"] / max(frames, 1) * 1e6,
            "rx_us": live["listener_cpu_s"] / max(frames, 1) * 1e6,
            "frames": frames, "lost_counter": live["counters"]["frames_lost"]}


def run_fast(rate: float, seconds: float) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp, Setup(Path(tmp)) as s:
        sender = s.sender(rate, seconds, seed=2)
        d = s.daemon(seconds + 60.0, cold=False, period=2.0 / rate)
        time.sleep(8.0)  # the daemon's start (warm)
        _, _, cpu1 = _proc(d)
        _go(sender)
        sent = _finish(sender, seconds + 120)
        time.sleep(3.0)  # the frames in flight
        _, _, cpu2 = _proc(d)
        d.terminate()
        live = _finish(d, 60)["daemon"]
    return {"sent": sent["sent"], "rate": sent["sent"] / sent["seconds"],
            "frames": live["frames"], "overflow": live["rx_overflow"],
            "lost_counter": live["counters"]["frames_lost"],
            "cpu_us": (cpu2 - cpu1) / max(live["frames"], 1) * 1e6,
            "est_us": live["estimator_cpu_s"] / max(live["frames"], 1) * 1e6,
            "rx_us": live["listener_cpu_s"] / max(live["frames"], 1) * 1e6}


def _verdict(ok: bool) -> str:
    return "met" if ok else "NOT met"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=60.0,
                    help="seconds of the 1 kHz run (default 60)")
    ap.add_argument("--fast-rate", type=float, default=GOAL_RATE,
                    help="frames/s of the loss run (default 18000)")
    ap.add_argument("--fast-seconds", type=float, default=10.0,
                    help="seconds of the loss run (default 10)")
    ap.add_argument("--send", metavar="URL", help=argparse.SUPPRESS)
    ap.add_argument("--rate", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--seconds", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--seed", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.send:
        send(args.send, args.rate, args.seconds, args.seed)
        return 0
    print(f"canrls run -i remote (python-can-remote on 127.0.0.1), n = 8 ({EFFECTS}), "
          f"float + fixed-point RLS; {os.cpu_count()} CPUs, load average "
          f"{', '.join(f'{x:.2f}' for x in os.getloadavg())}")
    a = run_1khz(args.duration)
    print(f"1 kHz (2000 frames/s), {a['frames']} frames:")
    print(f"  first parameter frame after a cold start  {a['first_s']:6.2f} s    "
          f"goal < {GOAL_START_S:g} s: {_verdict(a['first_s'] < GOAL_START_S)}")
    print(f"  resident memory after {args.duration:g} s            {a['rss_mb']:6.1f} MB   "
          f"goal < {GOAL_RSS_MB:g} MB: {_verdict(a['rss_mb'] < GOAL_RSS_MB)} "
          f"(peak {a['hwm_mb']:.1f} MB)")
    print(f"  CPU per frame, the daemon's process       {a['cpu_us']:6.1f} us   "
          f"goal < {GOAL_CPU_US:g} us: {_verdict(a['cpu_us'] < GOAL_CPU_US)} "
          f"(of which its threads: estimator {a['est_us']:.1f} us, bus listener "
          f"{a['rx_us']:.1f} us, python-can-remote's client included)")
    b = run_fast(args.fast_rate, args.fast_seconds)
    lost = b["sent"] - b["frames"]
    print(f"{args.fast_rate:.0f} frames/s offered for {args.fast_seconds:g} s "
          f"(the sender reached {b['rate']:.0f} frames/s):")
    print(f"  frames lost                               {lost:6.0f}      goal 0: "
          f"{_verdict(lost == 0 and b['rate'] >= 0.99 * args.fast_rate)} "
          f"({b['sent']} sent, {b['frames']} processed, queue overflow {b['overflow']}; "
          f"losses the counter check inferred from arrival times: {b['lost_counter']})")
    print(f"  CPU per frame, the daemon's process       {b['cpu_us']:6.1f} us   "
          f"(estimator {b['est_us']:.1f} us, bus listener {b['rx_us']:.1f} us)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
