#!/usr/bin/env python3
"""Soak: the daemon through a long run of simulated 1 kHz traffic with random faults.

Prints figures and a verdict; it is not a unit test (``tests/test_tools.py`` runs a
few simulated seconds of it). One process: the real :class:`~canrls.live.daemon.Daemon`
as ``canrls run`` builds it (:func:`canrls.cli.run.daemon_for`; its published fixed
column the target's integer path, ``--fixed kernel`` the kernel's) on a python-can
``virtual`` bus, fed by the simulated drive (``canrls.sim``; two
feedback frames per 1 ms control period) as fast as the daemon takes the frames, the
frames keeping their simulated timestamps (they go straight into the daemon's receive
queue of the virtual channel, as ``tools/bench_daemon.py`` does; the feeder waits
while more than ``--backlog`` frames are queued; the daemon takes blocks of at most
:data:`MAX_BLOCK` frames). A listener on the same channel decodes what the daemon
publishes (``canrls.can.estimator_frames.FrameDecoder``).

The faults (``--faults``, the syntax of :mod:`canrls.sim.faults`, seeded by
``--seed``) are injected into the drive's frames: dropped, corrupted (bad CRC), bad
alive counters, bad DLCs, duplicated and reordered frames, receive-clock steps back
and forward, bursts of command frames (random and valid, chosen so that they leave
the estimates as they were) and bus error frames. The daemon is never restarted.

With ``--axes N`` (N > 1) the soak runs a machine: N simulated drives, each its own
seed (``--seed`` + 1000 k), parameters (inertia scaled by 1 + 0.5 k, friction by
1 + 0.25 k: :func:`canrls.sim.machine.axis_params`), feedback IDs (the default DBC's
+ k x 0x10, the ``offset:`` ID rule) and own frames (+ k x 0x40), all on one virtual bus
served by one :class:`~canrls.live.machine_daemon.MachineDaemon` (one daemon per axis,
one bus connection, one reader routing each frame by its ID). Each drive's frames get
faults of their own (its seed; its commands on its axis's ``RlsCommand`` ID), but for
the receive-clock steps: the machine's one receiver stamps every frame, so its clock
steps (seeded by ``--seed``, as many a second as on one drive's frames) hit the
frames of all axes at once; each axis counts those on its frames and on the error
frames. The drives' frames are interleaved chunk by chunk, each drive's in its own
order. Each axis is judged against the same axis of a fault-free twin machine; an
error frame reaches every axis (it is the bus's), so each axis must have taken its own
frames and every error frame on the bus.

Then a fault-free twin runs: the same drive, the same seed, no faults, another
daemon. Printed (per axis with ``--axes N``):

* frames processed, and the faults injected, by kind, beside what the daemon counted
  (rejected frames by reason, frames lost, commands answered, error frames);
* faults survived: the faults in the frames the daemon processed while it kept
  running and publishing (all of them, unless it stopped or stalled);
* parameters lost: each published parameter of the faulted run against the twin's,
  the difference in units of the twin's sigma, and both against the drive's truth,
  judged by both criteria (``CRITERIA``, each printed with its verdict per parameter):
  *literal*, lost when further than 2 sigma from the twin, and *accuracy*, lost when
  further from the truth than the twin by more than 2 sigma (the fixed point: 2 sigma
  beyond its resolution floor, the twin's own fixed-minus-float gap); not finite or not
  published after the last frame is lost by both. The verdict takes ``--criterion``
  (default :data:`CRITERION`, the hardening issue's "within 2 sigma of a fault-free
  run"; *accuracy* judges what a fault must not do even where sigma, after an hour
  below the estimator's own bias on this drive, is too small for that:
  ``compare``, docs/reliability.md);
* resident memory (``VmRSS``) at start and at each tenth of the run, its peak
  (``VmHWM``) and the slope of a straight line through the tenths (2nd to 10th);
* the process's peak RSS (``VmHWM``) and its threads at the start, while the faulted
  run served and at the end (both runs' daemons stopped);
* ``PASSED`` or ``FAILED`` against the criteria (of the whole machine with ``--axes
  N``: the first line of the verdict block, each axis's verdict after it): every frame
  processed, the daemon alive and publishing after the last frame without a restart,
  no parameter lost, memory flat (the RSS grew by at most ``--flat-mb`` MB over the
  second half of the run), and as many threads at the end as at the start. Exit
  status 0 when passed, 1 when failed.

Usage::

    nice python tools/soak.py [--duration 3600] [--seed 1] [--faults SPEC] [--axes N]
                              [--effects inertia,viscous,coulomb,offset,unbalance,cogging:6]
                              [--fixed target]
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import logging
import math
import os
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np
from can.interfaces import virtual as _virtual

from canrls.can.estimator_frames import FrameDecoder, ParameterReport, frame_ids
from canrls.can.frameblock import FrameBlock
from canrls.can.idrules import IdRule
from canrls.cli.run import daemon_for
from canrls.core.errors import CanrlsError
from canrls.live.bus_link import command_id, moved
from canrls.live.daemon import Daemon, wait_until
from canrls.live.daemon_settings import FIXED_PATHS, DaemonSettings
from canrls.live.machine_daemon import MachineDaemon
from canrls.processor.axes import OWN_STEP, check_own
from canrls.processor.config import AppConfig, prepare
from canrls.sim.faults import ERROR_CLASSES, FaultInjector, FaultLog, FaultSpec
from canrls.sim.machine import AXIS_ID_STEP, MAX_SIM_AXES, axis_params
from canrls.sim.scenario import Simulator, scenario

#: n = 8 parameters, as tools/bench_daemon.py
EFFECTS = "inertia,viscous,coulomb,offset,unbalance,cogging:6"
#: the daemon's ``max_block`` here: the hour is fed in about a minute, so the estimator
#: would take blocks of up to the default 65,536 frames (33 s of traffic; a live daemon
#: at 1 kHz takes some 200 a block). Its scratch buffers (decoder outputs, the pairer's
#: work arrays, the raw regressors), kept between blocks and grown to the largest block
#: yet, then grew whenever a larger block than ever came, at a random moment of the run:
#: the RSS steps of 1-3 MB that made "memory flat" fail by chance. With this bound they
#: reach it in the first minutes (docs/reliability.md).
MAX_BLOCK = 4096
#: 3 600 to 7 200 faults of every kind to the hour of 7.2 million frames, a clock step
#: every 50 s and a burst of up to 64 commands every 30 s on average, an error frame
#: every 15 s, and half a second of silence every 5 minutes
FAULTS = ("drop=0.001,dup=0.0005,reorder=0.0005,corrupt=0.001,silence=0.5s@100s/300s,"
          "counter=0.001,dlc=0.0005,tstep=3e-6,tstep_max=0.5s,cmd=5e-6,cmd_burst=64,"
          "errframe=1e-5")
#: the kinds printed, in order, with what the daemon has to count for each
KINDS = ("dropped", "silenced", "corrupted", "miscounted", "resized", "duplicated",
         "reordered", "clock_steps", "commands", "error_frames")
SIGMAS = 2.0
#: what loses a parameter (``--criterion``); both are always printed
CRITERIA = {"literal": "lost when |faulted - twin| > 2 sigma",
            "accuracy": "lost when |faulted - truth| - |twin - truth| > 2 sigma"}
#: the verdict's criterion (docs/reliability.md, *Within 2 sigma of the twin: the gap fills*)
CRITERION = "literal"
_ch = itertools.count()


def rss_mb(field_name: str = "VmRSS") -> float:
    """``VmRSS`` (or another field of /proc/self/status) of this process [MB]."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(field_name + ":"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


class Published(can.Listener):
    """What one axis's daemon publishes: parameters, status, acknowledgements (counted);
    its own frames are the shipped DBC's IDs + ``own_offset``."""

    def __init__(self, own_offset: int = 0) -> None:
        self.decoder = FrameDecoder()
        self.lock = threading.Lock()
        self.frames = 0
        self.acks: Counter[str] = Counter()
        #: time.monotonic() of the last RlsEstimate frame
        self.last_estimate = 0.0
        self._offset = own_offset
        self._own = frozenset(i + own_offset for i in frame_ids().own)
        self._estimate_id = frame_ids().estimate + own_offset

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_extended_id or msg.arbitration_id not in self._own:
            return  # another axis's, or a drive's
        with self.lock:
            self.frames += 1
            n = len(self.decoder.acks)
            self.decoder.feed(moved(msg, -self._offset) if self._offset else msg)
            if len(self.decoder.acks) > n:
                ack = self.decoder.acks.pop()
                self.acks[ack.result.name.lower()] += 1
            if msg.arbitration_id == self._estimate_id:
                self.last_estimate = time.monotonic()

    def table(self) -> dict[str, ParameterReport]:
        with self.lock:
            return {r.name or f"#{r.index}": r for r in self.decoder.table()}


@dataclass
class RunResult:
    """One axis of one run of the daemon (faulted or fault-free)."""

    label: str
    frames_offered: int = 0
    frames_processed: int = 0
    alive: bool = True
    published_after_end: bool = False
    why: str = ""
    stats: dict[str, Any] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)
    lost: int = 0
    faults: FaultLog = field(default_factory=FaultLog)
    survived: dict[str, int] = field(default_factory=dict)
    params: dict[str, ParameterReport] = field(default_factory=dict)
    #: the simulated drive's true value of every published parameter (NaN: none)
    truth: dict[str, float] = field(default_factory=dict)
    acks: dict[str, int] = field(default_factory=dict)


@dataclass
class MachineRun:
    """One run of the daemon serving every axis (one axis without ``--axes``)."""

    label: str
    axes: dict[str, RunResult] = field(default_factory=dict)
    rss: list[tuple[float, float]] = field(default_factory=list)  # (simulated s, MB)
    rss_peak: float = float("nan")
    wall_s: float = 0.0
    log_records: dict[str, int] = field(default_factory=dict)
    #: threads of the process while the daemon served (after the last frame)
    threads: int = 0
    #: frames on the machine's bus that no axis took (a machine of axes only)
    foreign: int = 0
    #: the steps of the bus's receive clock (a machine of axes only)
    clock: FaultLog | None = None


@dataclass(frozen=True)
class AxisPlan:
    """One simulated drive and the daemon's axis serving it: name, seed (noise and
    faults), the ID rule of its feedback frames, the offset of its own frames and its
    true parameters (:func:`canrls.sim.machine.axis_params`)."""

    name: str
    seed: int
    rule: IdRule
    own_offset: int
    params: dict[str, float]


def plan(n: int, seed: int, effects: str) -> tuple[AxisPlan, ...]:
    """The ``n`` drives of a soak: axis k (0-based) seed ``seed + 1000 k``, feedback on
    the default DBC's IDs + k x 0x10, own frames + k x 0x40; axis 0 is the one drive
    of a soak without ``--axes``."""
    return tuple(AxisPlan(f"axis{k + 1}", seed + 1000 * k, IdRule("offset", k * AXIS_ID_STEP),
                          k * OWN_STEP, axis_params(effects, k)) for k in range(n))


class _LogCount(logging.Handler):
    """Counts the daemon's log records by level; ERROR and above go to stderr."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.counts: Counter[str] = Counter()

    def emit(self, record: logging.LogRecord) -> None:
        self.counts[record.levelname] += 1
        if record.levelno >= logging.ERROR:
            sys.stderr.write(f"  [daemon log] {record.levelname} {record.getMessage()}\n")


def make_daemon(channel: str, effects: str, fixed: str = DaemonSettings().fixed,
                max_block: int = MAX_BLOCK, axis: AxisPlan | None = None) -> Daemon:
    """The daemon of the drive (``axis`` None), or of one axis of a machine (its own
    feedback IDs and own frames, taking only its frames from the machine's bus), built
    as ``canrls run`` builds it, its published fixed column ``fixed`` (``[daemon] fixed``)."""
    cfg = AppConfig()
    cfg.model = {"effects": effects.split(","), "kt": 0.1}
    protocol, model, est = prepare(cfg)
    # commands on explicitly: the soak floods them (the default may be off)
    settings = DaemonSettings(commands=True, queue_size=200_000, max_block=max_block,
                              fixed=fixed)
    if axis is not None:
        protocol = protocol.with_ids(axis.rule)
        settings = dataclasses.replace(settings, own_offset=axis.own_offset, rx_filter=True)
    return daemon_for(protocol, model, est, settings,
                      bus={"interface": "virtual", "channel": channel}, backpressure=True)


class _Axis:
    """One axis while it runs: its drive, its daemon, what it published, the frames
    offered to it and the faults so far at each chunk it has not processed past.
    ``clock``: the bus's receive clock (a machine's: its steps hit every axis's frames
    at once), None: the drive's own (one drive)."""

    def __init__(self, p: AxisPlan, duration: float, faults: FaultSpec, effects: str,
                 fixed: str, channel: str, clock: FaultInjector | None) -> None:
        machine = clock is not None
        self.plan = p
        self.clock = clock
        self.scenario = scenario("standard", effects=effects, seed=p.seed, duration=duration,
                                 excitation="standard", params=p.params, faults=faults if
                                 clock is None else dataclasses.replace(faults, tstep=0.0))
        self.daemon = make_daemon(channel, effects, fixed, axis=p if machine else None)
        proto = self.daemon.protocol
        self.sim = Simulator(self.scenario, t0=0.0, protocol=proto if machine else None,
                             command_id=command_id(p.own_offset))
        self.watcher = Published(p.own_offset)
        #: the frames this axis takes (None: every frame, a drive's own daemon)
        self.ids = np.array(sorted({m.frame_id for m in proto.messages}
                                   | {command_id(p.own_offset)}), np.uint32) \
            if machine else None
        self.offered = 0
        # frames offered, faults so far (those the daemon processed past are dropped)
        self.marks: deque[tuple[int, dict[str, int]]] = deque()

    def offer(self, block: FrameBlock) -> None:
        """Count the frames of ``block`` (the bus's) this axis takes: its own IDs and
        every error frame."""
        if self.ids is None:
            self.offered += len(block)
        else:
            self.offered += int(np.count_nonzero(
                block.is_error | (~block.is_extended & np.isin(block.arbitration_id,
                                                                self.ids))))
        self.marks.append((self.offered, self.fault_log().counts()))

    def fault_log(self) -> FaultLog:
        """The drive's faults, and the bus's clock steps on this axis's frames."""
        log = self.sim.fault_log
        if self.clock is None:
            return log
        assert self.ids is not None  # an axis of a machine takes its own IDs
        on = self.clock.log.per_id["clock_steps"]
        mine = {*self.ids.tolist(), *ERROR_CLASSES}
        return dataclasses.replace(log, clock_steps=sum(c for i, c in on.items() if i in mine),
                                   clock_offset=self.clock.log.clock_offset)

    def processed_past(self, frames: int) -> None:
        """Drop the marks the daemon processed past: only the last of them can still be
        the answer (the harness's own bookkeeping must not grow with the run)."""
        while len(self.marks) > 1 and self.marks[1][0] <= frames:
            self.marks.popleft()

    def result(self, label: str, published_after_end: bool) -> RunResult:
        d = self.daemon
        res = RunResult(label, frames_offered=self.offered,
                        published_after_end=published_after_end)
        s = d.stats()
        res.frames_processed = s.frames
        res.stats = s.to_dict()
        fr = d.processor.frame_counts()
        res.rejected = {k: v for k, v in fr.rejected.items() if v}
        res.lost = sum(fr.lost.values())
        res.faults = self.fault_log()
        res.survived = {}
        if published_after_end:  # faults in the frames the daemon processed
            for n, counts in self.marks:
                if n <= res.frames_processed:
                    res.survived = counts
        res.params = self.watcher.table()
        res.truth = {name: float(self.scenario.truth.get(name, math.nan))
                     for name in res.params}
        res.acks = dict(self.watcher.acks)
        return res


def interleave(blocks: Sequence[FrameBlock]) -> FrameBlock:
    """The drives' blocks of one chunk on one bus: frame i of a block of n at i / n of
    the chunk, each drive's frames in their own order (its reordered frames kept), the
    first drive's first at equal places."""
    if len(blocks) == 1:
        return blocks[0]
    key = np.concatenate([np.arange(len(b)) / max(len(b), 1) for b in blocks])
    return FrameBlock.concat(list(blocks)).take(np.argsort(key, kind="stable"))


def run(label: str, duration: float, seed: int, faults: str, effects: str,
        backlog: int = 40_000, tenths: int = 10, stall_s: float = 120.0,
        progress: Callable[[str], None] | None = None, axes: int = 1,
        fixed: str = DaemonSettings().fixed) -> MachineRun:
    """Feed ``duration`` simulated seconds of ``axes`` drives, with ``faults``, to a
    daemon (one axis) or to a machine's daemons on one bus (``axes`` > 1), each
    publishing the fixed column ``fixed`` (``[daemon] fixed``)."""
    res = MachineRun(label)
    ch = f"soak-{os.getpid()}-{next(_ch)}"
    many = axes > 1
    spec = FaultSpec.parse(faults)
    # a machine's receive clock is the bus's: one injector of clock steps for all axes,
    # as many steps a second as on one drive's frames (the bus carries N times the frames)
    clock = FaultInjector(FaultSpec(tstep=spec.tstep / axes, tstep_max=spec.tstep_max),
                          seed=(seed, 2), t0=0.0) if many else None
    counter = _LogCount()
    logging.getLogger("canrls").addHandler(counter)
    live = [_Axis(p, duration, spec, effects, fixed, ch, clock)
            for p in plan(axes, seed, effects)]
    daemons = [a.daemon for a in live]
    server: Daemon | MachineDaemon = (MachineDaemon({a.plan.name: a.daemon for a in live})
                                      if many else daemons[0])
    dt = live[0].scenario.dt
    alive, why = True, ""
    published: list[bool] = [False] * len(live)
    t_wall = time.perf_counter()
    listener_bus: can.BusABC | None = None
    notifier: can.Notifier | None = None
    try:
        server.start()
        listener_bus = can.Bus(interface="virtual", channel=ch, ignore_config=True)
        notifier = can.Notifier(listener_bus, [a.watcher for a in live], timeout=0.1)
        own = listener_bus.queue  # type: ignore[attr-defined]  # a VirtualBus's receive queue
        with _virtual.channels_lock:  # the daemon's receive queue, not the listener's
            queues = [q for q in _virtual.channels[ch] if q is not own]
        res.rss.append((0.0, rss_mb()))
        next_mark = duration / tenths
        offered = 0
        last_progress, last_frames = time.monotonic(), -1
        # chunks of at most 5 s, and at least 20 to the run (the tenths of the RSS)
        chunk = int(max(50, min(5000, duration / dt / 20)))
        for blocks in zip(*(a.sim.frames(chunk) for a in live), strict=True):
            bus_block = interleave(blocks)
            if clock is not None:
                bus_block = clock.apply(bus_block)
            msgs = bus_block.to_messages()
            for q in queues:
                for m in msgs:
                    q.put_nowait(m)
            offered += len(msgs)
            for a in live:
                a.offer(bus_block)
            # as fast as the daemons take them
            while True:
                stats = [d.stats() for d in daemons]
                waiting = sum(s.backlog for s in stats) + sum(q.qsize() for q in queues)
                if waiting <= backlog:
                    break
                now = time.monotonic()
                frames = sum(s.frames for s in stats)
                if frames != last_frames:
                    last_frames, last_progress = frames, now
                elif now - last_progress > stall_s:
                    alive = False
                    why = f"the daemon took no frame for {stall_s:g} s (stalled)"
                    break
                time.sleep(0.005)
            if not alive:
                break
            for a, s in zip(live, stats, strict=True):
                a.processed_past(s.frames)
            t_sim = float(live[0].sim.k) * dt
            if t_sim >= next_mark - 1e-9:
                res.rss.append((t_sim, rss_mb()))
                if progress is not None:
                    progress(f"{label}: {t_sim:7.0f} s simulated, {offered} frames, "
                             f"RSS {res.rss[-1][1]:.1f} MB, {time.perf_counter() - t_wall:.0f} s")
                next_mark += duration / tenths

        # the rest of the frames, then a publication that includes them
        def behind() -> list[str]:
            out = []
            for a in live:
                s = a.daemon.stats()
                if s.frames < a.offered or s.backlog:
                    out.append(f"{a.offered - s.frames} frames" + (
                        f" of {a.plan.name}" if many else ""))
            return out

        if alive and not wait_until(lambda: not behind(), stall_s):
            alive = False
            why = f"{', '.join(behind())} not processed {stall_s:g} s after the last"
        done = time.monotonic()
        hold = max(d.config.fault_hold_s + 3 * d.config.publish_interval
                   for d in daemons) + 2.0
        end = done + hold
        while time.monotonic() < end and not all(a.watcher.last_estimate > done for a in live):
            time.sleep(0.02)
        time.sleep(0.2)  # the rest of that publication
        published = [a.watcher.last_estimate > done for a in live]
        res.threads = threading.active_count()
        res.axes = {a.plan.name: a.result(label, pub) for a, pub in zip(live, published,
                                                                       strict=True)}
        for r in res.axes.values():
            r.alive, r.why = alive, why
        res.rss_peak = rss_mb("VmHWM")
        if isinstance(server, MachineDaemon):
            res.foreign = server.foreign_frames
        if clock is not None:
            res.clock = clock.log
    finally:
        if notifier is not None:
            notifier.stop()
        if listener_bus is not None:
            listener_bus.shutdown()
        server.stop()
        logging.getLogger("canrls").removeHandler(counter)
    res.log_records = dict(counter.counts)
    res.wall_s = time.perf_counter() - t_wall
    return res


def slope_mb_per_h(rows: list[tuple[float, float]]) -> float:
    """Least-squares slope of RSS against simulated time, from the first tenth on."""
    pts = [(t, m) for t, m in rows[1:] if math.isfinite(m)]
    if len(pts) < 2:
        return float("nan")
    t, m = np.array(pts).T
    if np.ptp(t) == 0:
        return float("nan")
    return float(np.polyfit(t / 3600.0, m, 1)[0])


def compare(faulted: RunResult, free: RunResult, truth: Mapping[str, float] | None = None
            ) -> list[tuple[str, str, float, float, str]]:
    """(name, which, difference in sigma, value, verdict) of every parameter of the
    fault-free run, fixed point and float reference; verdict '' when kept.

    The difference is faulted minus fault-free in the twin's sigma. With the drive's
    ``truth`` known (the simulator's), a parameter is lost when the faults left it
    further from the truth than the twin by more than 2 sigma:
    ``|faulted - truth| - |fault-free - truth| > 2 sigma``. Without a true value it is
    held to ``|faulted - fault-free| <= 2 sigma``. The scale is honest either way: after
    an hour sigma is smaller than the estimator's own bias on this drive (inertia 13
    sigma from the truth in the twin), and which samples the faults take away, and
    the straight lines that fill the gaps, reweight that bias by more than sigma; a
    fault costs a parameter when it makes it less accurate (docs/reliability.md).
    """
    rows = []
    for name, ref in free.params.items():
        got = faulted.params.get(name)
        sigma = ref.sigma
        true = math.nan if truth is None else float(truth.get(name, math.nan))
        for which in ("fixed_value", "float_value"):
            r = getattr(ref, which)
            g = None if got is None else getattr(got, which)
            if got is None or g is None or (which == "fixed_value" and not got.valid):
                rows.append((name, which, math.nan, math.nan, "not published"))
                continue
            if not math.isfinite(g):
                rows.append((name, which, math.nan, g, "not finite"))
                continue
            if r is None or sigma is None or not math.isfinite(r) or not sigma > 0:
                rows.append((name, which, math.nan, g, "no reference"))
                continue
            z = (g - r) / sigma
            # the float reference is held to 2 sigma; the fixed point to 2 sigma beyond
            # its own resolution floor, measured by the twin: |fixed - float| of the
            # fault-free run (theta's LSB outlasts a shrinking sigma after an hour at
            # lambda = 1: docs/reliability.md)
            floor = 0.0
            if which == "fixed_value" and ref.float_value is not None \
                    and math.isfinite(ref.float_value):
                floor = abs(r - ref.float_value) / sigma
            bound = SIGMAS + floor
            if math.isfinite(true):
                # worse = (|g - truth| - |r - truth|) / sigma: the accuracy the faults cost
                worse = (abs(g - true) - abs(r - true)) / sigma
                verdict = "" if worse <= bound else f"worse by {worse:.3g} > {bound:.3g} sigma"
            else:
                verdict = "" if abs(z) <= bound else f"> {bound:.3g} sigma"
            rows.append((name, which, z, g, verdict))
    return rows


def _judged(a: RunResult, b: RunResult
            ) -> tuple[dict[str, list[tuple[str, str, float, float, str]]], dict[str, list[str]]]:
    """Both criteria's rows (:func:`compare`) and, of each, the parameters lost."""
    judged = {"literal": compare(a, b, None), "accuracy": compare(a, b, b.truth)}
    return judged, {c: sorted({r[0] for r in rows if r[4]}) for c, rows in judged.items()}


def axis_figures(args: argparse.Namespace, a: RunResult, b: RunResult,
                 log_records: Mapping[str, int] | None = None) -> list[str]:
    """One axis's figures against its twin: frames, faults injected and counted, faults
    survived, each parameter by both criteria (``log_records``: the daemon's, printed
    with its counters when it is the only axis)."""
    out = []
    fl = a.faults
    out.append(f"frames processed: {a.frames_processed} of {a.frames_offered} offered "
               f"(twin: {b.frames_processed} of {b.frames_offered}); samples "
               f"{a.stats.get('samples')} (twin {b.stats.get('samples')}); blocks "
               f"{a.stats.get('blocks')}, publications {a.stats.get('publications')}")
    counts = fl.counts()
    total = sum(counts[k] for k in KINDS)
    out.append(f"faults injected: {total} ({fl.command_bursts} command bursts, clock offset at "
               f"the end {fl.clock_offset:+.3f} s)")
    for k in KINDS:
        out.append(f"  {k:13s} {counts[k]:9d}")
    st = a.stats
    rej = ", ".join(f"{k} {v}" for k, v in sorted(a.rejected.items())) or "none"
    out.append(
        f"the daemon counted: frames rejected {sum(a.rejected.values())} ({rej}); frames "
        f"lost by the counter check {a.lost} (twin {b.lost}); commands {st.get('commands')} "
        f"(rejected {st.get('commands_rejected')}), acknowledgements seen "
        f"{sum(a.acks.values())} ({', '.join(f'{k} {v}' for k, v in sorted(a.acks.items()))});"
        f" error frames {st.get('error_frames')}; frames not sent while the bus was faulty "
        f"{st.get('tx_paused')}; bus reopened {st.get('bus_reopens')} times; queue overflow "
        f"{st.get('rx_overflow')}"
        + ("" if log_records is None else f"; log records {dict(log_records) or '{}'}"))
    surv = sum(a.survived.get(k, 0) for k in KINDS)
    why = f"stopped: {a.why}" if a.why else "published nothing after the end"
    out.append(f"faults survived: {surv} of {total}"
               + ("" if a.alive and a.published_after_end else f" (the daemon {why})"))
    # both criteria, always: the literal one (|faulted - twin| <= 2 sigma) and the
    # accuracy one (no further from the truth than the twin by more than 2 sigma)
    judged, beyond = _judged(a, b)
    rows = judged[args.criterion]
    lost = beyond[args.criterion]
    out.append(f"parameters lost: {len(lost)} of {len(b.params)}"
               + (f" ({', '.join(lost)})" if lost else "")
               + f" by the {args.criterion} criterion ({CRITERIA[args.criterion]}); faulted "
               "minus fault-free in the fault-free run's sigma, then both criteria's verdicts "
               "[criterion: fixed/float]:")
    for name in b.params:
        fx = next(r for r in rows if r[0] == name and r[1] == "fixed_value")
        fv = next(r for r in rows if r[0] == name and r[1] == "float_value")
        marks = "[" + ", ".join(
            f"{c}: " + "/".join("lost" if next(r for r in judged[c] if r[0] == name
                                               and r[1] == w)[4] else "kept"
                                for w in ("fixed_value", "float_value"))
            for c in ("literal", "accuracy")) + "]"
        ref = b.params[name]
        sigma = ref.sigma if ref.sigma is not None and ref.sigma > 0 else math.nan
        rfix = ref.fixed_value if ref.fixed_value is not None else math.nan
        rflt = ref.float_value if ref.float_value is not None else math.nan
        true = b.truth.get(name, math.nan)
        out.append(f"  {name:16s} fixed {fx[3]: .7g} vs {rfix: .7g}: {fx[2]:+7.2f} sigma "
                   f"{fx[4]:15s} float {fv[2]:+7.2f} sigma {fv[4]:15s} (sigma {sigma:.3g}; "
                   f"fault-free fixed - float {(rfix - rflt) / sigma:+.2f} sigma; float minus "
                   f"truth {true:.7g}: faulted {(fv[3] - true) / sigma:+.2f}, fault-free "
                   f"{(rflt - true) / sigma:+.2f} sigma) {marks}")
    return out


def axis_criteria(args: argparse.Namespace, a: RunResult, b: RunResult) -> list[str]:
    """Each criterion met or not on one axis, the verdict's named."""
    judged, beyond = _judged(a, b)
    out = []
    for c in ("literal", "accuracy"):
        zs = [abs(r[2]) for r in judged[c] if r[1] == "float_value" and math.isfinite(r[2])]
        out.append(f"criterion {c} ({CRITERIA[c]}): "
                   + ("met" if not beyond[c] and b.params else
                      f"not met ({', '.join(beyond[c]) or 'nothing published'})")
                   + (f"; largest |faulted - twin| {max(zs):.2f} sigma (float)" if zs else "")
                   + ("; the verdict's" if c == args.criterion else ""))
    return out


def axis_checks(args: argparse.Namespace, a: RunResult, b: RunResult) -> dict[str, bool]:
    """The verdict's criteria that hold of one axis and its twin."""
    lost = _judged(a, b)[1][args.criterion]
    return {
        "every frame processed": a.frames_processed == a.frames_offered and a.alive,
        "alive and publishing after the last frame, no restart": (
            a.alive and a.published_after_end and a.stats.get("bus_reopens") == 0),
        f"no parameter lost ({args.criterion})": not lost and bool(b.params),
        "the fault-free twin ran through": (b.alive and b.published_after_end
                                            and b.frames_processed == b.frames_offered),
    }


@dataclass(frozen=True)
class Process:
    """The process around both runs: peak RSS (``VmHWM``) [MB] and threads, at the
    start and at the end (both runs' daemons stopped)."""

    peak_start: float
    peak_end: float
    threads_start: int
    threads_end: int


def report(args: argparse.Namespace, a: MachineRun, b: MachineRun, proc: Process) -> bool:
    """Print the figures; True when the soak passed."""
    many = len(a.axes) > 1
    print("soak: " + (f"{len(a.axes)} axes on one bus (a daemon each, one machine), "
                       if many else "")
          + f"{args.duration:g} s of simulated 1 kHz traffic (2 frames per period"
          + (" and axis" if many else "") + f"), seed {args.seed}, model {args.effects}, "
          f"the fixed column the {args.fixed}'s; "
          f"{a.wall_s:.0f} s wall (twin {b.wall_s:.0f} s); {os.cpu_count()} CPUs, load "
          f"{', '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(("faults (each drive's own): " if many else "faults: ")
          + str(FaultSpec.parse(args.faults)))
    plans = {p.name: p for p in plan(len(a.axes), args.seed, args.effects)}
    checks: dict[str, list[str]] = {}  # criterion -> the axes that miss it
    for name, ax in a.axes.items():
        tw = b.axes[name]
        for k, ok in axis_checks(args, ax, tw).items():
            checks.setdefault(k, []).extend([] if ok else [name])
        if not many:
            print("\n".join(axis_figures(args, ax, tw, a.log_records)))
            continue
        p = plans[name]
        print(f"{name}: feedback IDs {', '.join(f'{i:#x}' for i in feedback_ids(p))}, own frames "
              f"{frame_ids().estimate + p.own_offset:#x}.., command "
              f"{command_id(p.own_offset):#x}; seed {p.seed}; truth "
              + ", ".join(f"{k} {v:.4g}" for k, v in p.params.items()))
        for line in (*axis_figures(args, ax, tw), *axis_criteria(args, ax, tw)):
            print("  " + line)
    if many:
        steps = a.clock.clock_steps if a.clock is not None else 0
        off = a.clock.clock_offset if a.clock is not None else 0.0
        print(f"the machine: frames of no axis {a.foreign} (twin {b.foreign}); steps of the "
              f"bus's receive clock {steps} (offset at the end {off:+.3f} s; each axis counts "
              f"those on its frames and on error frames); log records {a.log_records or '{}'}")
    rss = a.rss
    half = [m for t, m in rss if t >= args.duration / 2 - 1e-9]
    growth = (rss[-1][1] - half[0]) if half else float("nan")
    slope = slope_mb_per_h(rss)
    print("RSS [MB] at each tenth of the run: "
          + ", ".join(f"{t:.4g} s {m:.1f}" for t, m in rss))
    print(f"RSS peak {a.rss_peak:.1f} MB, final {rss[-1][1]:.1f} MB; slope from the first tenth "
          f"on {slope:+.2f} MB per simulated hour; growth over the second half {growth:+.1f} MB")
    print(f"process: peak RSS {proc.peak_start:.1f} MB at the start, {proc.peak_end:.1f} MB at "
          f"the end; threads {proc.threads_start} at the start, {a.threads} while the faulted "
          f"run served (twin {b.threads}), {proc.threads_end} at the end")
    if not many:
        ax = next(iter(a.axes.values()))
        print("\n".join(axis_criteria(args, ax, b.axes[next(iter(a.axes))])))
    keys = list(checks)
    ordered: dict[str, bool | list[str]] = {k: checks[k] for k in keys[:3]}
    ordered[f"memory flat (<= {args.flat_mb:g} MB over the second half)"] = (
        math.isfinite(growth) and growth <= args.flat_mb)
    ordered[keys[3]] = checks[keys[3]]
    if many:
        ordered["every frame on the bus taken by its axis"] = a.foreign == 0 and b.foreign == 0
    ordered[f"threads back to {proc.threads_start} at the end"] = (
        proc.threads_end == proc.threads_start)
    # a criterion of every axis: met when no axis misses it
    failed = [k + (f" ({', '.join(v)})" if many and isinstance(v, list) else "")
              for k, v in ordered.items() if v is False or (isinstance(v, list) and v)]
    ok = not failed
    print(("PASSED" if ok else "FAILED") + ": " + (
        "; ".join(ordered) if ok else "not met: " + "; ".join(failed)))
    if many:
        for name, ax in a.axes.items():
            miss = [k for k, v in axis_checks(args, ax, b.axes[name]).items() if not v]
            print(f"  {name}: " + ("passed" if not miss else "failed: " + "; ".join(miss)))
    return ok


def feedback_ids(p: AxisPlan) -> list[int]:
    """The feedback IDs of axis ``p`` (the default DBC's moved by its rule)."""
    return [p.rule.frame_id(i, False, "soak") for i in frame_ids().feedback]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=3600.0,
                    help="simulated seconds of 1 kHz traffic (default 3600)")
    ap.add_argument("--seed", type=int, default=1,
                    help="seed of the drive's noise and of the faults (default 1; axis k of "
                         "--axes: seed + 1000 k)")
    ap.add_argument("--axes", type=int, default=1, metavar="N",
                    help="simulated drives, each its own seed, parameters, feedback IDs "
                         "(+ k x 0x10) and faults (the receive clock's steps: the bus's), "
                         "served by one daemon per axis on one bus "
                         "(default 1: one drive, one daemon; at most 20, axis k's own "
                         "frames moved by k x 0x40)")
    ap.add_argument("--faults", default=FAULTS,
                    help=f"fault spec (canrls.sim.faults; default {FAULTS})")
    ap.add_argument("--effects", default=EFFECTS, help=f"drive and model (default {EFFECTS})")
    ap.add_argument("--flat-mb", type=float, default=2.0,
                    help="most RSS growth over the second half of the run [MB] (default 2)")
    ap.add_argument("--backlog", type=int, default=40_000,
                    help="frames queued before the feeder waits (default 40000)")
    ap.add_argument("--criterion", choices=tuple(CRITERIA), default=CRITERION,
                    help=f"what loses a parameter in the verdict (default {CRITERION}; both "
                         f"are printed): " + "; ".join(f"{k}: {v}" for k, v in CRITERIA.items()))
    ap.add_argument("--fixed", choices=FIXED_PATHS, default=DaemonSettings().fixed,
                    help="[daemon] fixed: the published fixed column (default: the daemon's "
                         "default, the target's integer path; 'kernel' for comparison)")
    ap.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    args = ap.parse_args(argv)
    if not (math.isfinite(args.duration) and args.duration > 0):
        ap.error(f"--duration {args.duration:g}: must be a number of seconds > 0")
    try:
        FaultSpec.parse(args.faults)  # a bad spec: one line before anything runs
    except CanrlsError as e:
        ap.error(f"--faults: {e}")
    if not 1 <= args.axes <= MAX_SIM_AXES:
        ap.error(f"--axes {args.axes}: 1 to {MAX_SIM_AXES} simulated drives")
    try:
        axes = plan(args.axes, args.seed, args.effects)
    except CanrlsError as e:
        ap.error(f"--effects: {e}")
    try:  # every axis's own frames on free IDs, as `canrls run` checks a machine
        protocol = prepare(AppConfig())[0]
        check_own({p.name: protocol.with_ids(p.rule) for p in axes},
                  {p.name: p.own_offset for p in axes},
                  "the soak moves axis k's own frames by k x 0x40: fewer axes")
    except CanrlsError as e:
        ap.error(f"--axes {args.axes}: {e}")

    def progress(line: str) -> None:
        if not args.quiet:
            print(line, file=sys.stderr, flush=True)

    peak, threads = rss_mb("VmHWM"), threading.active_count()
    a = run("faulted", args.duration, args.seed, args.faults, args.effects, args.backlog,
            progress=progress, axes=args.axes, fixed=args.fixed)
    b = run("fault-free", args.duration, args.seed, "none", args.effects, args.backlog,
            progress=progress, axes=args.axes, fixed=args.fixed)
    proc = Process(peak, rss_mb("VmHWM"), threads, threading.active_count())
    return 0 if report(args, a, b, proc) else 1


if __name__ == "__main__":
    raise SystemExit(main())
