"""``canrls demo --axes N``: the demo's story on a machine of N simulated drives on one bus.

One axis, picked by the seed, has an effect its model lacks; the others have none. The
machine is the simulated one on a bus of its own (python-can interface ``canrls-sim`` with
``axes=N``, faster than real time: :func:`canrls.sim.machine.machine`, axis k on the
default DBC's IDs + k x 0x10), one daemon per axis serving it
(:class:`~canrls.live.machine_daemon.MachineDaemon`, each axis its own frames and own IDs,
+ k x 0x40), and a listener on a ``virtual`` bus of the same channel reading what they
publish as any tool would. After 40 % of the time the drives are held, each axis's
feedback recorded from the bus is diagnosed, the effect the diagnosis names is added
with an ``RlsCommand`` on that axis's command ID only, and each axis's residual RMS (its
``RlsStatus``) is compared before and after. The first line printed is the answer; the
story follows.
"""

from __future__ import annotations

import math
import os
import struct
import sys
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from canrls.cli.demo_common import BASE as _BASE
from canrls.cli.demo_common import diagnosis
from canrls.cli.run import daemon_for
from canrls.core.errors import ConfigError

if TYPE_CHECKING:
    from canrls.live.daemon import Daemon

__all__ = ["AxisStory", "MachineDemoResult", "run_machine_demo"]

@dataclass
class AxisStory:
    """One axis of the machine demo: the effect it hides ("" none), the one the diagnosis
    named (None none), the residual RMS before and after the fix and its final model."""

    name: str
    hidden: str
    diagnosed: str | None
    rms_before: float
    rms_after: float
    effects: list[str]

    @property
    def change(self) -> float:
        """Relative change of the residual RMS (-0.8: a fifth of what it was)."""
        return self.rms_after / self.rms_before - 1.0 if self.rms_before > 0 else math.nan


@dataclass
class MachineDemoResult:
    """What the machine demo found (:func:`run_machine_demo`)."""

    axes: list[AxisStory]
    #: the axis the effect was added to (None: the diagnosis named none)
    fixed_axis: str | None
    added: str | None
    unit: str
    wall_s: float
    sim_s: float
    answer: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"answer": self.answer, "fixed_axis": self.fixed_axis, "added": self.added,
                "unit": self.unit, "wall_s": self.wall_s, "sim_s": self.sim_s,
                "axes": {a.name: {"hidden": a.hidden, "diagnosed": a.diagnosed,
                                  "rms_before": a.rms_before, "rms_after": a.rms_after,
                                  "change": a.change, "effects": a.effects}
                         for a in self.axes}}


def run_machine_demo(n: int = 4, duration: float = 30.0, seed: int = 1,
                     hidden: str = "unbalance", out: TextIO | None = None,
                     timeout: float = 600.0) -> MachineDemoResult:
    """Run the machine demo; print the answer, then the story, to ``out`` (default
    stdout); return the figures."""
    import can

    from canrls.can.estimator_frames import (
        CommandCode,
        encode_command,
        frame_ids,
        parse_effect,
    )
    from canrls.live.bus_link import command_id, moved
    from canrls.live.daemon_settings import DaemonSettings
    from canrls.live.machine_daemon import MachineDaemon
    from canrls.live.monitor_listener import LibraryUnits
    from canrls.processor.axes import OWN_STEP
    from canrls.processor.config import AppConfig, prepare
    from canrls.sim.machine import MAX_SIM_AXES, kind_protocol, machine
    from canrls.sim.plant import parse_effects

    if not 2 <= n <= MAX_SIM_AXES:
        raise ConfigError(f"--axes {n}: the machine demo has 2 to {MAX_SIM_AXES} axes")
    if not (math.isfinite(duration) and duration >= 10.0):
        raise ConfigError(f"--duration: {duration!r} must be at least 10 simulated seconds")
    hidden = ",".join(parse_effects(hidden))
    if hidden in _BASE or "," in hidden:
        raise ConfigError(f"--hidden: {hidden!r} must be one effect not among {', '.join(_BASE)}")
    which = int(np.random.default_rng(seed).integers(n))
    hides = [hidden if k == which else "" for k in range(n)]
    axes = machine(n, duration=duration, seed=seed, hidden=hides)  # what the bus simulates
    lines: list[str] = []
    say: Callable[[str], None] = lines.append
    base = kind_protocol("offset")
    cfg = AppConfig()
    cfg.model = {"effects": list(_BASE), "kt": axes[0].scenario.truth.kt}
    _, model, settings = prepare(cfg)
    unit = LibraryUnits.for_model(model).output_unit()
    channel = f"canrls-demo-axes-{os.getpid()}-{time.monotonic_ns()}"
    bus = {"interface": "canrls-sim", "channel": channel, "axes": n, "seed": seed,
           "duration": duration, "hidden": ",".join(hides), "realtime": False,
           "start_time": 0.0}
    daemons: dict[str, Daemon] = {}
    for k, a in enumerate(axes):
        dset = DaemonSettings(publish_interval=0.05, block_interval=0.005, commands=True,
                              own_offset=k * OWN_STEP, rx_filter=True, queue_size=20000)
        protocol = base.with_ids(a.rule)
        daemons[a.name] = daemon_for(protocol, model, settings, dset, bus=bus,
                                     backpressure=True)
    md = MachineDaemon(daemons)
    say(f"{n} simulated drives on one bus (canrls-sim), seed {seed}, {duration:g} s "
        f"simulated; each axis's model knows only {', '.join(_BASE)}:")
    for k, a in enumerate(axes):
        say(f"  {a.name}: feedback on the default IDs + {k * 0x10:#x}, own frames + "
            f"{k * OWN_STEP:#x}; {a.scenario.truth.summary()}")
    fix_at = 0.4 * duration
    ids = {a.name: frozenset(m.frame_id for m in daemons[a.name].protocol.messages)
           for a in axes}
    tl = _Timeline(ids, {a.name: frame_ids().status + k * OWN_STEP
                         for k, a in enumerate(axes)}, daemons)
    t_wall = time.monotonic()
    diagnosed: dict[str, str | None] = {}
    fixed_axis = added = None
    md.start()
    tool = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    notifier = can.Notifier(tool, [tl], timeout=0.1)
    try:
        _advance(tl, fix_at, timeout)
        for d in daemons.values():
            d.hold_input(True)  # the drives wait while the diagnosis runs
        before = {a.name: tl.mean(a.name, fix_at / 2, fix_at) for a in axes}
        say("")
        say(f"1. Residual RMS of each axis after {tl.sim_t:.0f} s (its RlsStatus):")
        for a in axes:
            floor = a.scenario.noise_floor
            say(f"  {a.name}: {before[a.name]:.3g} {unit} ({before[a.name] / floor:.1f}x the "
                f"sensor noise of {floor:.2g} {unit})")
        say("")
        say("2. Diagnosis of each axis's feedback recorded from the bus:")
        everything = tl.take()
        for a in axes:
            mine = [m for m in everything if m.arbitration_id in ids[a.name]]
            report = diagnosis(mine, daemons[a.name].protocol, model, settings)
            sugg = str(report.suggestion[0]) if report is not None and report.suggestion \
                else None
            diagnosed[a.name] = sugg
            say(f"  {a.name}: " + (f"{sugg} is missing" if sugg else "nothing missing"))
        del everything
        found = {name: s for name, s in diagnosed.items() if s}
        named = [(k, a) for k, a in enumerate(axes) if a.name in found]
        say("")
        if named:
            k, a = max(named, key=lambda ka: before[ka[1].name])
            fixed_axis, added = a.name, found[a.name]
            eid, order = parse_effect(found[a.name])
            own = command_id(k * OWN_STEP)
            say(f"3. RlsCommand add_effect {added} to {a.name} only (ID {own:#x}):")
            tool.send(moved(encode_command(CommandCode.ADD_EFFECT, eid, order), k * OWN_STEP))
            d = daemons[a.name]
            # its command comes through the machine's one bus, which every held axis holds
            # up: all drives go on
            for x in daemons.values():
                x.hold_input(False)
            if not d.wait_for(lambda x: added in x.model.effect_names, 30.0):
                say(f"  {a.name} did not add {added} within 30 s")
            say(f"  {a.name} now estimates {', '.join(d.model.effect_names)}; the others "
                f"{', '.join(_BASE)}")
        else:
            say("3. The diagnosis names no effect on any axis: nothing is added.")
        for d in daemons.values():
            d.hold_input(False)
        t_fix = tl.sim_t
        _advance(tl, duration, timeout)
        say("")
        say(f"4. Residual RMS of each axis before and after (until {tl.sim_t:.0f} s):")
        stories = []
        for a in axes:
            after = tl.mean(a.name, t_fix + (tl.sim_t - t_fix) / 2, tl.sim_t)
            s = AxisStory(a.name, a.hidden, diagnosed[a.name], before[a.name], after,
                          list(daemons[a.name].model.effect_names))
            stories.append(s)
            say(f"  {a.name}: {s.rms_before:.3g} -> {s.rms_after:.3g} {unit} "
                f"({s.change * 100:+.0f} %)" + (f"   {added} added" if a.name == fixed_axis
                                                 else ""))
    finally:
        notifier.stop()
        tool.shutdown()
        md.stop()
    wall = time.monotonic() - t_wall
    say("")
    say(f"({wall:.1f} s wall clock for {tl.sim_t:.0f} s of a simulated machine)")
    answer = _answer(stories, fixed_axis, added, {a.name: a.scenario.noise_floor for a in axes})
    w = out or sys.stdout
    w.write("\n".join([answer, *lines]) + "\n")
    w.flush()
    return MachineDemoResult(stories, fixed_axis, added, unit, wall, tl.sim_t, answer)


class _Timeline:
    """A listener on a ``virtual`` bus of the machine's channel: each axis's residual RMS
    from its RlsStatus, dated by that axis's own time (the periods its daemon has taken:
    the drives run ahead of a slower axis's daemon), and the feedback frames until
    :meth:`take`."""

    def __init__(self, feedback: dict[str, frozenset[int]], status: dict[str, int],
                 daemons: Mapping[str, Daemon]) -> None:
        self.feedback = frozenset().union(*feedback.values())
        self.status = {fid: name for name, fid in status.items()}
        self.daemons = daemons
        self.rms: dict[str, list[tuple[float, float]]] = {n: [] for n in status}
        self._frames: list[Any] | None = []
        self._lock = threading.Lock()

    def time(self, name: str) -> float:
        """Axis ``name``'s time [s]: the periods of feedback its daemon has taken."""
        d = self.daemons[name]
        # t = frames / (frames per period) * period
        return d.stats().frames / len(d.protocol.messages) * (d.dt or 1e-3)

    @property
    def sim_t(self) -> float:
        """The machine's time: its slowest axis's."""
        return min(self.time(n) for n in self.daemons)

    def __call__(self, msg: Any) -> None:
        aid = msg.arbitration_id
        if aid in self.feedback:
            with self._lock:
                if self._frames is not None:
                    self._frames.append(msg)
        elif aid in self.status and not msg.is_error_frame:
            name = self.status[aid]
            # RlsStatus: ResidualRms float32 at byte 0
            rms = struct.unpack_from("<f", bytes(msg.data), 0)[0]
            with self._lock:
                self.rms[name].append((self.time(name), rms))

    def take(self) -> list[Any]:
        """The feedback frames so far; none are kept after."""
        with self._lock:
            frames, self._frames = self._frames or [], None
        return frames

    def mean(self, name: str, t0: float, t1: float) -> float:
        """Mean RMS of axis ``name`` published between ``t0`` and ``t1`` s (NaN: none)."""
        with self._lock:
            vals = [r for t, r in self.rms[name] if t0 <= t <= t1 and math.isfinite(r)]
        return sum(vals) / len(vals) if vals else math.nan


def _advance(tl: _Timeline, until: float, timeout: float) -> None:
    """Until every axis's time reaches ``until`` s (or the machine's end: no axis moves
    for 2 s), then two publications more: each RlsStatus covers what was taken."""
    end = time.monotonic() + timeout
    last, still = -1.0, time.monotonic()
    while (now := tl.sim_t) < until - 2e-3:
        time.sleep(0.01)
        if now != last:
            last, still = now, time.monotonic()
        elif time.monotonic() - still > 2.0:
            break  # the machine's duration is over
        if time.monotonic() > end:
            raise TimeoutError("the simulated machine did not advance")
    time.sleep(0.15)


def _answer(stories: list[AxisStory], fixed_axis: str | None, added: str | None,
            floors: dict[str, float]) -> str:
    """The first line: which axis lacked what, how its error fell, the others' state."""
    others = [s for s in stories if s.name != fixed_axis]
    if fixed_axis is None:
        return f"canrls demo: no effect diagnosed on any of the {len(stories)} axes"
    s = next(s for s in stories if s.name == fixed_axis)
    near = [o.rms_after / floors[o.name] for o in others]
    return (f"canrls demo: {fixed_axis} lacks {added}; added to it alone, its residual RMS "
            f"fell {-s.change * 100:.0f} % ({s.rms_before / floors[s.name]:.1f}x -> "
            f"{s.rms_after / floors[s.name]:.1f}x the sensor noise); the other {len(others)} "
            f"axes kept their model, at {min(near):.1f}-{max(near):.1f}x theirs")
