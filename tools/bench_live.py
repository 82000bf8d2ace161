#!/usr/bin/env python3
"""The live figures of issue 14 (item 6), each printed against its goal, with real processes.

Prints figures; it is not a test. Everything is bound to 127.0.0.1. Two transports:

**The SocketCAN receive path** (the deployment's; this kernel has no ``AF_CAN``, no
vcan). ``canrls run -i socketcan`` runs as its own process, and its bus is python-can's
own :class:`~can.interfaces.socketcan.SocketcanBus`, whose receive code
(``select``, ``recvmsg`` with the ``SO_TIMESTAMPNS`` control message,
``dissect_can_frame``, ``Message(...)``) and send code (``build_can_frame``,
``select``, ``send``) run unchanged on a UDP socket bound to 127.0.0.1 instead of a raw
CAN socket: the datagrams are the 16-byte ``struct can_frame`` of python-can's
``build_can_frame``. Stood in: the socket (the kernel's UDP path, not its CAN path)
and the bus's constructor, which would open ``AF_CAN`` (:func:`udp_socketcan_bus` sets
the attributes it sets; in the daemon's process python-can's ``socketcan`` interface
name is pointed at it). The daemon reads it as it reads a SocketCAN bus: by default with
its block reader (``canrls.live.bus_link.BlockReader``: ``recvmmsg`` on python-can's socket
into the arrays of a frame block, ``canrls._rx``, no ``can.Message`` per frame), and,
for comparison, with ``[daemon] rx_bulk = false`` (python-can's ``recv`` frame by frame,
``BusReader``; skipped with ``--skip-message-path``); the receive buffer it was granted
(``[daemon] rx_buffer``, from its log) is printed. A sender process puts the simulated
drive's frames on the daemon's port at 2,000 frames/s (1 kHz: a current and a speed
frame each millisecond) for ``--socketcan-seconds`` and at ``--fast-rate`` (18,000) for
``--fast-seconds``, every ``--tick`` (``--fast-tick``; both 1 ms) the frames due by then
(a bus delivers them one by one: at 18,000 frames/s 1 ms hand-overs of 18 frames spare
the listener most of its wake-ups, so that figure is a lower bound); the parameter
frames the daemon sends go back to the sender, which counts them. Printed: the daemon's
CPU per frame over the timed window (the process from /proc, goal 20 us, and its
estimator and bus reader threads from /proc/PID/task), frames sent against frames
processed (goal: none lost), the datagrams the socket's receive buffer dropped, the
parameter frames sent and received. Then, for comparison (skipped with
``--skip-floor``), the same run with python-can's ``Notifier`` alone on that bus, feeding
a listener that only counts
(:func:`floor_udp`): the CPU per frame of python-can's receive path and the operating
system's wake-ups, one for each hand-over (the daemon's readers take every frame
waiting and sleep ``rx_interval``, 5 ms, between wake-ups, so they can go below that
floor).

**python-can-remote, the test transport** (the transport of the tests): four processes

1. a python-can-remote server (``python -m can_remote``, a virtual bus behind it);
2. a sender (this script with ``--send``, a python-can client of the server) putting
   the simulated drive's feedback frames on the bus at a fixed rate (two frames per
   control period; the frames are simulated before the clock starts);
3. ``canrls run -i remote`` (the daemon, n = 8 parameters, float and fixed point);
4. this script, a client that only keeps the parameter frames the daemon publishes.

Two runs:

* **1 kHz** (2,000 frames/s) for ``--duration`` seconds (default 60). The sender runs
  before the daemon starts (a drive on the bus), and the daemon starts cold: a fresh
  process with an empty ``$HOME`` and cache directory. Figures:
  the time from the daemon's start to the first parameter frame on the bus (goal 3 s);
  its resident memory after ``--duration`` seconds (or 5 s after the first parameter
  frame, if that came later; ``VmRSS``, goal 100 MB; the peak
  ``VmHWM`` beside it); its CPU per frame in the steady state, the whole process from
  /proc, python-can-remote's pure-Python websocket client included (for information:
  the goal of 20 us is the SocketCAN path's), and beside it the daemon's estimator
  thread and bus listener thread (the bus reader, which runs the websocket client) over
  the whole run, from ``canrls run --json``.
* **18,000 frames/s** (twice a saturated 1 Mbit/s bus) for ``--fast-seconds``
  (default 10): frames the sender sent against frames the daemon processed (goal: none
  lost), the daemon's queue overflow, and its CPU per frame at that rate. The frames
  carry the server's arrival times, so the alive-counter check may infer losses from
  the websocket's stalls; that count is printed beside, for information (the
  SocketCAN runs' counter gaps likewise: their timestamps are the times the daemon's
  socket received them, in bursts of one hand-over and after the sender's stalls).

Usage::

    python tools/bench_live.py [--duration 60] [--fast-seconds 10] [--fast-rate 18000]
                               [--socketcan-seconds 30] [--tick 0.001]
                               [--skip-remote | --skip-socketcan]
                               [--skip-message-path] [--skip-floor]
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import re
import select
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import can
from can.bus import CanProtocol
from can.interfaces import BACKENDS
from can.interfaces.socketcan import constants as sc_constants
from can.interfaces.socketcan.socketcan import SocketcanBus, build_can_frame

from bench_daemon import EFFECTS, _messages
from canrls.can.estimator_frames import frame_ids
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
        if cold:  # a fresh home: nothing of an earlier run anywhere
            home = self.tmp / f"home-{len(self.procs)}"
            home.mkdir()
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
    try:
        return json.loads(out)  # the daemon's --json, or the sender's last line
    except json.JSONDecodeError:
        return json.loads(out.strip().splitlines()[-1])


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


# ---------------------------------------------------------------- SocketCAN over UDP
#: the only address the SocketCAN stand-in uses
LOOPBACK = "127.0.0.1"


def udp_socketcan_bus(channel: str, **kwargs: Any) -> SocketcanBus:
    """python-can's :class:`SocketcanBus`, its receive and send code unchanged, on a UDP
    socket bound to 127.0.0.1 instead of an ``AF_CAN`` raw socket (which this kernel
    lacks). ``channel``: ``"RXPORT>PEERPORT"`` (both on 127.0.0.1).

    What runs per frame is python-can's own: ``BusABC.recv`` -> ``_recv_internal``
    (``select``) -> ``capture_message`` (``recvmsg`` with the ``SO_TIMESTAMPNS`` control
    message, ``dissect_can_frame``, ``Message(...)``); ``send`` -> ``build_can_frame``,
    ``select``, ``socket.send``. Stood in: the socket (UDP datagrams of the 16-byte
    ``struct can_frame``; the kernel's UDP path instead of its CAN path), and the
    constructor, which would open ``AF_CAN``: the attributes it sets are set here as it
    sets them for one classic-CAN channel without filters (the kernel filter then
    passes everything, so ``_is_filtered`` is true). Parameter frames go to the peer
    port (the sender, which counts them).
    """
    if kwargs.get("fd") or kwargs.get("can_filters"):
        raise SystemExit("error: the SocketCAN stand-in has no CAN FD and no filters")
    rx_port, peer_port = (int(x) for x in channel.split(">"))
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    # as SocketcanBus.__init__: nanosecond receive timestamps
    sock.setsockopt(socket.SOL_SOCKET, sc_constants.SO_TIMESTAMPNS, 1)
    sock.bind((LOOPBACK, rx_port))
    sock.connect((LOOPBACK, peer_port))  # send() goes there, recv only from there
    bus = SocketcanBus.__new__(SocketcanBus)
    bus.socket = sock
    bus.channel = channel
    bus.channel_info = f"python-can socketcan code over UDP {LOOPBACK}:{rx_port}"
    bus._bcm_sockets = {}
    bus._is_filtered = True  # set_filters(None) on AF_CAN: the kernel passes all
    bus._task_id = 0
    bus._task_id_guard = threading.Lock()
    bus._can_protocol = CanProtocol.CAN_20
    bus._periodic_tasks = []  # BusABC.__init__
    bus._filters = None
    bus._is_shutdown = False
    return bus


def udp_port() -> int:
    """A free UDP port on 127.0.0.1."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((LOOPBACK, 0))
        return int(s.getsockname()[1])


def udp_drops(port: int) -> int:
    """Datagrams the kernel dropped at the UDP socket bound to 127.0.0.1:``port``
    (receive buffer full; ``drops``, the last column of /proc/net/udp)."""
    local = f"0100007F:{port:04X}"
    with open("/proc/net/udp") as fh:
        for line in fh:
            f = line.split()
            if len(f) > 2 and f[1] == local:
                return int(f[-1])
    return -1


def send_udp(port: int, daemon_port: int, rate: float, seconds: float, seed: int,
             tick: float) -> None:
    """The sender of the SocketCAN run: the frames as python-can's ``build_can_frame``
    packs them (``struct can_frame``), one datagram each, to the daemon's port at
    ``rate`` frames/s, every ``tick`` seconds the frames due by then. It reads (counts)
    the parameter frames the daemon sends back, until told to stop (a line on stdin;
    its socket stays open until then, so the daemon's sends never meet a closed port).
    Prints what it sent, then what it received (JSON lines)."""
    msgs = _messages(seconds * rate / 2000.0 + 0.01, seed)[:int(seconds * rate)]
    frames = [build_can_frame(m) for m in msgs]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind((LOOPBACK, port))
        sock.setblocking(False)
        dest = (LOOPBACK, daemon_port)
        received = 0

        def drain() -> int:
            k = 0
            while select.select([sock], [], [], 0)[0]:
                sock.recv(128)
                k += 1
            return k

        def until_told() -> int:  # reading the parameter frames
            k = 0
            while True:
                ready = select.select([sock, sys.stdin], [], [], 1.0)[0]
                k += drain()
                if sys.stdin in ready:
                    sys.stdin.readline()
                    return k

        print(json.dumps({"ready": True}), flush=True)
        received += until_told()  # go
        t0 = time.perf_counter()
        k, step, n = 0, 0, len(frames)
        while k < n:
            step += 1
            target = min(n, int((time.perf_counter() - t0) * rate) + 1)
            for i in range(k, target):
                sock.sendto(frames[i], dest)
            k = max(k, target)
            received += drain()
            wait = t0 + step * tick - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
        took = time.perf_counter() - t0
        print(json.dumps({"sent": n, "seconds": took}), flush=True)
        received += until_told()  # the daemon has stopped
    print(json.dumps({"received": received}), flush=True)


def _name_threads() -> None:
    """Every thread started from now on gets its Python name as its OS name
    (/proc/PID/task/TID/comm), so the benchmark can read each thread's CPU time."""
    libc = ctypes.CDLL(None, use_errno=True)
    bootstrap = threading.Thread._bootstrap_inner  # type: ignore[attr-defined]

    def named(self: threading.Thread) -> None:
        libc.prctl(15, self.name.encode()[:15], 0, 0, 0)  # PR_SET_NAME
        bootstrap(self)

    threading.Thread._bootstrap_inner = named  # type: ignore[attr-defined]


class _Count(can.Listener):
    def __init__(self) -> None:
        self.n = 0

    def on_message_received(self, msg: can.Message) -> None:
        self.n += 1


def floor_udp(channel: str) -> int:
    """The floor of the SocketCAN run: the same bus, read by python-can's ``Notifier``
    (as the daemon's ``BusLink`` starts it) into a listener that only counts; no
    estimator. Prints ready, then, after a line on stdin, the frames counted."""
    _name_threads()
    bus = udp_socketcan_bus(channel)
    count = _Count()
    notifier = can.Notifier(bus, [count], timeout=0.1)
    try:
        print(json.dumps({"ready": True}), flush=True)
        sys.stdin.readline()
    finally:
        notifier.stop()
        bus.shutdown()
    print(json.dumps({"daemon": {"frames": count.n}}), flush=True)
    return 0


def serve_udp(argv: list[str]) -> int:
    """The daemon's process of the SocketCAN run: ``canrls run -i socketcan ...`` itself
    (its command line, ``argv``), with python-can's ``socketcan`` interface built by
    :func:`udp_socketcan_bus` in this process."""
    BACKENDS["socketcan"] = ("__main__", "udp_socketcan_bus")
    _name_threads()
    from canrls.cli.main import main as canrls_main
    sys.argv = [sys.argv[0], *argv]  # the process's own command line, as the console script
    return int(canrls_main() or 0)


def _thread_cpu(pid: int) -> dict[str, float]:
    """CPU time [s] (user + system) of each thread of process ``pid``, by OS name."""
    out: dict[str, float] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            name = (task / "comm").read_text().strip()
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue  # the thread ended
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / CLK_TCK
    return out


def run_socketcan(rate: float, seconds: float, tick: float, floor: bool = False,
                  bulk: bool = True) -> dict[str, Any]:
    """``canrls run`` on the SocketCAN stand-in, warm, fed ``seconds`` at ``rate``
    (``floor``: instead of the daemon, python-can's notifier alone, :func:`floor_udp`;
    ``bulk``: the daemon's SocketCAN block reader, else ``[daemon] rx_bulk = false``,
    python-can's ``recv`` frame by frame)."""
    dport, sport = udp_port(), udp_port()
    sender = subprocess.Popen(
        [PY, __file__, "--send-udp", str(sport), "--daemon-port", str(dport),
         "--rate", str(rate), "--seconds", str(seconds), "--seed", "4", "--tick", str(tick)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert sender.stdout is not None
    try:
        json.loads(sender.stdout.readline())  # ready: its port is bound (the daemon's
        # parameter frames to a port not yet bound would make its socket report
        # ECONNREFUSED, as a connected UDP socket does, and the bus would be reopened)
    except BaseException:
        sender.kill()
        sender.wait()
        raise
    channel = f"{dport}>{sport}"
    period = [] if rate == 2000.0 else ["--period", repr(2.0 / rate)]
    conf = []
    if not bulk:
        tmp = tempfile.NamedTemporaryFile("w", suffix=".toml", delete=False)
        with tmp:
            tmp.write("[daemon]\nrx_bulk = false\n")
        conf = ["-C", tmp.name]
    cmd = ([PY, __file__, "--floor-udp", channel] if floor else
           [PY, __file__, "--serve-udp", "--log-level", "INFO", "run", "-i", "socketcan",
            "-c", channel, *conf, "--effects", EFFECTS, "--kt", "0.1",
            "--duration", f"{seconds + 120:g}", "--json", *period])
    d = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    err = ""
    try:
        if floor:
            assert d.stdout is not None
            json.loads(d.stdout.readline())  # ready
            time.sleep(1.0)
        else:
            time.sleep(8.0)  # the daemon's start (warm)
        _, _, cpu1 = _proc(d)
        th1 = _thread_cpu(d.pid)
        _go(sender)
        sent = json.loads(sender.stdout.readline())
        time.sleep(1.0)  # the last block (block_interval 0.1 s)
        _, _, cpu2 = _proc(d)
        th2 = _thread_cpu(d.pid)
        drops = udp_drops(dport)
        if floor:
            _go(d)
        else:
            d.terminate()
        out, err = d.communicate(timeout=60)
        if d.returncode != 0:
            sys.stderr.write(err)
            raise SystemExit(f"error: {' '.join(map(str, d.args))} exited {d.returncode}")
        try:
            live = json.loads(out)["daemon"]  # the daemon's --json
        except json.JSONDecodeError:
            live = json.loads(out.strip().splitlines()[-1])["daemon"]  # the floor's line
        _go(sender)  # stop reading
        sent.update(_finish(sender, 30))
    finally:
        for p in (sender, d):
            if p.poll() is None:
                p.kill()
                p.wait()
        if conf:
            os.unlink(conf[1])
    # the daemon's log line: "...: receive buffer N bytes (asked M)" or the warning
    granted = re.search(r"receive buffer (\d+) bytes \(asked|granted (\d+)", err)
    reader = re.search(r"read by (\w+)", err)
    frames = live["frames"]
    per = 1e6 / max(sent["sent"], 1)

    def thread(prefix: str) -> float:
        return sum(v - th1.get(k, 0.0) for k, v in th2.items() if k.startswith(prefix)) * per

    est, rx = thread("canrls estimat"), thread("Notifier" if floor else "canrls-bus-read")
    return {"sent": sent["sent"], "rate": sent["sent"] / sent["seconds"], "frames": frames,
            "drops": drops, "overflow": live.get("rx_overflow", 0),
            "lost_counter": live.get("counters", {}).get("frames_lost", 0),
            "param_frames": sent["received"], "frames_sent": live.get("frames_sent", 0),
            "cpu_us": (cpu2 - cpu1) * per, "est_us": est, "rx_us": rx,
            "other_us": (cpu2 - cpu1) * per - est - rx,
            "rcvbuf": int(next(g for g in granted.groups() if g)) if granted else None,
            "reader": reader.group(1) if reader else None}


def _verdict(ok: bool) -> str:
    return "met" if ok else "NOT met"


def main() -> int:
    if sys.argv[1:2] == ["--serve-udp"]:  # the daemon's process of the SocketCAN run
        return serve_udp(sys.argv[2:])
    if sys.argv[1:2] == ["--floor-udp"]:  # python-can's notifier alone on that bus
        return floor_udp(sys.argv[2])
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=60.0,
                    help="seconds of the 1 kHz run over python-can-remote (default 60)")
    ap.add_argument("--fast-rate", type=float, default=GOAL_RATE,
                    help="frames/s of the loss runs (default 18000)")
    ap.add_argument("--fast-seconds", type=float, default=10.0,
                    help="seconds of the loss runs (default 10)")
    ap.add_argument("--socketcan-seconds", type=float, default=30.0,
                    help="seconds of the 2,000 frames/s run on the SocketCAN receive path "
                         "(default 30)")
    ap.add_argument("--tick", type=float, default=1e-3,
                    help="seconds between the SocketCAN sender's hand-overs at 2,000 "
                         "frames/s (default 1 ms: a drive's two frames of a control "
                         "period back to back)")
    ap.add_argument("--fast-tick", type=float, default=1e-3,
                    help="seconds between the SocketCAN sender's hand-overs at --fast-rate "
                         "(default 1 ms; a bus delivers the frames one by one: a shorter "
                         "tick is closer to it, and costs more wake-ups)")
    ap.add_argument("--skip-remote", action="store_true",
                    help="only the SocketCAN receive path's runs")
    ap.add_argument("--skip-socketcan", action="store_true",
                    help="only python-can-remote's runs")
    ap.add_argument("--skip-message-path", action="store_true",
                    help="SocketCAN: not the comparison run with [daemon] rx_bulk = false")
    ap.add_argument("--skip-floor", action="store_true",
                    help="SocketCAN: not the comparison run of python-can's Notifier alone")
    ap.add_argument("--send", metavar="URL", help=argparse.SUPPRESS)
    ap.add_argument("--send-udp", type=int, metavar="PORT", help=argparse.SUPPRESS)
    ap.add_argument("--daemon-port", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--rate", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--seconds", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--seed", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.send:
        send(args.send, args.rate, args.seconds, args.seed)
        return 0
    if args.send_udp:
        send_udp(args.send_udp, args.daemon_port, args.rate, args.seconds, args.seed, args.tick)
        return 0
    print(f"canrls run, n = 8 ({EFFECTS}), float + fixed-point RLS; {os.cpu_count()} CPUs, "
          f"load average {', '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if not args.skip_socketcan:
        print("SocketCAN receive path (python-can's socketcan code over a UDP loopback socket; "
              "AF_CAN itself is not available here):")
        for rate, seconds, tick in ((2000.0, args.socketcan_seconds, args.tick),
                                    (args.fast_rate, args.fast_seconds, args.fast_tick)):
            print(f"  {rate:5.0f} frames/s offered for {seconds:g} s ({tick * 1e3:g} ms "
                  f"hand-overs):")
            paths = [("the block reader (rx_bulk = true, the default)", True)]
            if not args.skip_message_path:
                paths.append(("python-can's recv (rx_bulk = false)", False))
            for what, bulk in paths:
                r = run_socketcan(rate, seconds, tick, bulk=bulk)
                lost = r["sent"] - r["frames"]
                print(f"    {what}, read by {r['reader']}, receive buffer {r['rcvbuf']} "
                      f"bytes; the sender reached {r['rate']:.0f} frames/s:")
                print(f"      CPU per frame, the daemon's process   {r['cpu_us']:6.1f} us   "
                      f"goal < {GOAL_CPU_US:g} us: {_verdict(r['cpu_us'] < GOAL_CPU_US)} "
                      f"(of which its threads: estimator {r['est_us']:.1f} us, bus reader "
                      f"{r['rx_us']:.1f} us, the others {r['other_us']:.1f} us)")
                print(f"      frames lost                           {lost:6.0f}      goal 0: "
                      f"{_verdict(lost == 0 and r['rate'] >= 0.99 * rate)} "
                      f"({r['sent']} sent, {r['frames']} processed; dropped by the socket's "
                      f"receive buffer {r['drops']}, queue overflow {r['overflow']}, counter "
                      f"gaps {r['lost_counter']}; parameter frames {r['frames_sent']} sent, "
                      f"{r['param_frames']} received)")
            if args.skip_floor:
                continue
            f = run_socketcan(rate, seconds, tick, floor=True)
            print(f"    for comparison, python-can's Notifier alone on that bus (a listener "
                  f"that only counts, no estimator): {f['cpu_us']:.1f} us per frame, the "
                  f"process (its notifier thread {f['rx_us']:.1f} us; {f['frames']} of "
                  f"{f['sent']} frames)")
    if args.skip_remote:
        return 0
    print("test transport: canrls run -i remote (python-can-remote on 127.0.0.1, a "
          "pure-Python websocket client in the daemon):")
    a = run_1khz(args.duration)
    print(f"1 kHz (2000 frames/s), {a['frames']} frames:")
    print(f"  first parameter frame after a cold start  {a['first_s']:6.2f} s    "
          f"goal < {GOAL_START_S:g} s: {_verdict(a['first_s'] < GOAL_START_S)}")
    print(f"  resident memory after {args.duration:g} s            {a['rss_mb']:6.1f} MB   "
          f"goal < {GOAL_RSS_MB:g} MB: {_verdict(a['rss_mb'] < GOAL_RSS_MB)} "
          f"(peak {a['hwm_mb']:.1f} MB)")
    print(f"  CPU per frame, the daemon's process       {a['cpu_us']:6.1f} us   "
          f"(for information: the goal < {GOAL_CPU_US:g} us is judged on the SocketCAN "
          f"receive path) (of which its threads: estimator {a['est_us']:.1f} us, bus "
          f"listener {a['rx_us']:.1f} us, python-can-remote's client included)")
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
